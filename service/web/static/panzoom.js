// Pan and zoom of one element (`target`, a box of a fixed size in CSS pixels) inside a clipping `viewport`:
// drag pans, the wheel zooms around the cursor, two fingers pinch, a double click zooms in, and the keys + - 0
// and the arrows do the same from the keyboard. The state is one translate + one scale, applied as a CSS
// transform (transform-origin 0 0), so whatever the target shows (any image of the same footprint) keeps the view.
// Until the user moves it, the view is the fitted one, fitted again whenever the viewport changes size (also
// when it was hidden, hence of size 0, at setSize).

const WHEEL_RATE = 0.0015; // scale factor per wheel pixel: exp(-deltaY * rate)
const LINE_PX = 16;        // a wheel "line" (deltaMode 1) in pixels
const KEEP_PX = 48;        // at least this much of the target stays inside the viewport
const MAX_ZOOM = 16;       // screen pixels per target pixel at most
const MIN_ZOOM = 0.25;     // of the fitted scale
const STEP = 1.5;          // the buttons' and keys' zoom factor
const PAN_KEY_PX = 60;

export function panZoom(viewport, target, { onChange = () => {} } = {}) {
  let w = 1, h = 1;          // the target's box
  let x = 0, y = 0, s = 1;   // target pixel (u, v) is at viewport (x + s u, y + s v)
  let fitted = 1;
  let sized = false;         // setSize was called
  let moved = false;         // the user moved the view since the last fit
  const pointers = new Map(); // pointerId -> {x, y} in viewport coordinates

  function local(ev) {
    const r = viewport.getBoundingClientRect();
    return { x: ev.clientX - r.left, y: ev.clientY - r.top };
  }

  function clampPan() {
    const vw = viewport.clientWidth, vh = viewport.clientHeight;
    const keepX = Math.min(KEEP_PX, w * s), keepY = Math.min(KEEP_PX, h * s);
    x = Math.min(vw - keepX, Math.max(keepX - w * s, x));
    y = Math.min(vh - keepY, Math.max(keepY - h * s, y));
  }

  function apply(byUser = true) {
    moved ||= byUser;
    clampPan();
    target.style.transform = `translate(${x}px, ${y}px) scale(${s})`;
    onChange({ x, y, scale: s, fitted });
  }

  // zoom by `factor` keeping the target point under viewport point (cx, cy) where it is
  function zoomAt(factor, cx, cy) {
    const next = Math.min(MAX_ZOOM, Math.max(fitted * MIN_ZOOM, s * factor));
    const u = (cx - x) / s, v = (cy - y) / s;
    s = next;
    x = cx - u * s;
    y = cy - v * s;
    apply();
  }

  function reset() {
    const vw = viewport.clientWidth, vh = viewport.clientHeight;
    fitted = Math.min(vw / w, vh / h) || 1;
    s = fitted;
    x = (vw - w * s) / 2;
    y = (vh - h * s) / 2;
    moved = false;
    apply(false);
  }

  const resized = new ResizeObserver(() => {
    if (!sized || !viewport.clientWidth || !viewport.clientHeight) return;
    if (moved) apply(false);
    else reset();
  });
  resized.observe(viewport);

  function onWheel(ev) {
    ev.preventDefault();
    const dy = ev.deltaMode === 1 ? ev.deltaY * LINE_PX : ev.deltaY;
    const p = local(ev);
    zoomAt(Math.exp(-dy * WHEEL_RATE), p.x, p.y);
  }

  function onDown(ev) {
    if (ev.button !== 0 && ev.pointerType === "mouse") return;
    viewport.setPointerCapture(ev.pointerId);
    pointers.set(ev.pointerId, local(ev));
    viewport.classList.add("dragging");
  }

  function onMove(ev) {
    const before = pointers.get(ev.pointerId);
    if (!before) return;
    const now = local(ev);
    if (pointers.size === 1) {
      x += now.x - before.x;
      y += now.y - before.y;
      pointers.set(ev.pointerId, now);
      apply();
      return;
    }
    // two fingers: scale by the change of their distance around their midpoint, and follow the midpoint
    const [other] = [...pointers].filter(([id]) => id !== ev.pointerId).map(([, p]) => p);
    const d0 = Math.hypot(before.x - other.x, before.y - other.y);
    const d1 = Math.hypot(now.x - other.x, now.y - other.y);
    pointers.set(ev.pointerId, now);
    x += (now.x - before.x) / 2;
    y += (now.y - before.y) / 2;
    zoomAt(d0 > 0 ? d1 / d0 : 1, (now.x + other.x) / 2, (now.y + other.y) / 2);
  }

  function onUp(ev) {
    pointers.delete(ev.pointerId);
    if (!pointers.size) viewport.classList.remove("dragging");
  }

  function onDoubleClick(ev) {
    const p = local(ev);
    zoomAt(ev.shiftKey ? 1 / 2 : 2, p.x, p.y);
  }

  function onKey(ev) {
    const cx = viewport.clientWidth / 2, cy = viewport.clientHeight / 2;
    const keys = {
      "+": () => zoomAt(STEP, cx, cy), "=": () => zoomAt(STEP, cx, cy), "-": () => zoomAt(1 / STEP, cx, cy),
      0: reset, ArrowLeft: () => { x += PAN_KEY_PX; apply(); }, ArrowRight: () => { x -= PAN_KEY_PX; apply(); },
      ArrowUp: () => { y += PAN_KEY_PX; apply(); }, ArrowDown: () => { y -= PAN_KEY_PX; apply(); },
    };
    if (!keys[ev.key] || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    ev.preventDefault();
    keys[ev.key]();
  }

  // every listener the view adds, removed together by dispose()
  const listeners = [["wheel", onWheel, { passive: false }], ["pointerdown", onDown], ["pointermove", onMove],
    ["pointerup", onUp], ["pointercancel", onUp], ["dblclick", onDoubleClick], ["keydown", onKey]];
  for (const [type, fn, opts] of listeners) viewport.addEventListener(type, fn, opts);

  return {
    // the target's box (CSS pixels at scale 1), then the whole of it fitted into the viewport
    setSize(width, height) {
      w = width;
      h = height;
      target.style.width = `${w}px`;
      target.style.height = `${h}px`;
      sized = true;
      reset();
    },
    reset,
    zoom(factor) { zoomAt(factor, viewport.clientWidth / 2, viewport.clientHeight / 2); },
    scale: () => s,
    // the target point (u, v) under viewport point (px, py)
    toTarget(px, py) { return { u: (px - x) / s, v: (py - y) / s }; },
    local,
    dispose() {
      resized.disconnect();
      for (const [type, fn] of listeners) viewport.removeEventListener(type, fn);
    },
  };
}

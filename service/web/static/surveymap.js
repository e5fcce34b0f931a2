// The job page's survey map: the orthomosaic's preview, panned and zoomed (panzoom.js), with the water taken out
// or as photographed, or the elevation's hillshade, all of one footprint, so a switch keeps the view; a scale
// bar, the ground point under the cursor, what survey.json says (surveyfacts.js) and the GeoTIFFs to download.
import { panZoom } from "./panzoom.js";
import { facts, groundAt, groundPerPixel, isMetric, length, niceLength, notes } from "./surveyfacts.js";
import { bytes, el, errorText, message } from "./ui.js";

// The survey stage's files, as pipeline/job/layout.py names them (JobLayout.survey_result, .survey and the
// products in it; tests/service/test_web.py holds these to it).
const RESULT = "survey.json";
const REPORT = "output/report.json";
const DIR = "output/survey/";
const LAYERS = [ // [key, label, preview]
  ["dewatered", "without water", `${DIR}ortho.jpg`],
  ["water", "with water", `${DIR}ortho_water.jpg`],
  ["elevation", "elevation", `${DIR}dem_hillshade.png`],
];
const FILES = [ // [path, what it is]
  [`${DIR}ortho.tif`, "orthomosaic, water removed (GeoTIFF)"],
  [`${DIR}ortho_water.tif`, "orthomosaic as photographed (GeoTIFF)"],
  [`${DIR}ortho_confidence.tif`, "restoration confidence (GeoTIFF)"],
  [`${DIR}dem.tif`, "elevation model, float32 heights (GeoTIFF)"],
  [RESULT, "the survey's numbers (JSON)"],
];
const SCALE_BAR_PX = 120; // the scale bar's longest length on screen

// What of the survey a job's artifact list holds; null when nothing (then the page offers no map).
export function surveyProducts(artifacts) {
  const has = new Map((artifacts || []).map((a) => [a.path, a]));
  const layers = LAYERS.filter(([, , path]) => has.has(path));
  const files = FILES.filter(([path]) => has.has(path)).map(([path, what]) => ({ ...has.get(path), what }));
  if (!layers.length && !files.length) return null;
  return { layers, files, result: has.has(RESULT), report: has.has(REPORT) };
}

// survey.json, else the copy report.json keeps under "survey"; {} when neither can be read
async function readSurvey(products, io) {
  if (products.result) return (await io.fetchJson(RESULT)) || {};
  if (products.report) return (await io.fetchJson(REPORT))?.survey || {};
  return {};
}

async function whyNoDewatered(products, io) {
  const mode = products.report ? (await io.fetchJson(REPORT).catch(() => null))?.mode : null;
  return mode === "3dgs"
    ? "This job modelled no water (mode 3dgs), so there is no mosaic with the water taken out: the map shows the "
      + "photos as taken."
    : "This job wrote no mosaic with the water taken out (the log says why): the map shows the photos as taken.";
}

function factList(survey) {
  return el("dl", { class: "facts" }, facts(survey).flatMap((f) => [
    el("dt", {}, f.label),
    el("dd", { "data-fact": f.key, "data-value": f.value === null || f.value === undefined ? "" : String(f.value) },
      f.text)]));
}

function fileList(products, io, status) {
  return el("ul", { class: "smap-files" }, products.files.map((f) => el("li", {},
    el("button", { type: "button", class: "ghost small", "data-path": f.path,
      onclick: () => io.download(f.path, status) }, f.path.split("/").pop()),
    el("span", { class: "muted" }, ` ${f.what}, ${bytes(f.size)}`))));
}

// The map's elements: the layer choice and zoom buttons above, the viewport (image, scale bar, cursor readout)
// beside the side panel (facts, notes, downloads).
function frame(root) {
  const ui = {
    why: el("p", { class: "muted", "data-why": "", hidden: true }),
    img: el("img", { class: "smap-img", alt: "", draggable: "false" }),
    bar: el("div", { class: "smap-scale-bar" }),
    barLabel: el("span"),
    where: el("div", { class: "smap-where mono", hidden: true }),
    layers: el("div", { class: "seg", role: "radiogroup", "aria-label": "map layer" }),
    zoom: el("span", { class: "row" }),
    side: el("div", { class: "smap-side" }),
  };
  ui.scale = el("div", { class: "smap-scale", hidden: true }, ui.bar, ui.barLabel);
  ui.viewport = el("div", { class: "smap", tabindex: "0", role: "img",
    "aria-label": "survey map: drag to pan, wheel or + and - to zoom, 0 to fit" }, ui.img, ui.scale, ui.where);
  root.replaceChildren(el("div", { class: "row smap-tools" }, ui.layers, el("span", { class: "spacer" }), ui.zoom),
    ui.why, el("div", { class: "smap-grid" }, ui.viewport, ui.side));
  return ui;
}

function zoomButtons(ui, pz) {
  const button = (label, title, fn) => el("button", { type: "button", class: "ghost small", title,
    "data-zoom": title, onclick: fn }, label);
  ui.zoom.replaceChildren(button("+", "zoom in", () => pz.zoom(1.5)), button("−", "zoom out", () => pz.zoom(1 / 1.5)),
    button("reset", "fit", () => pz.reset()));
}

// the scale bar: the longest round ground length that fits SCALE_BAR_PX at the current zoom
function drawScaleBar(ui, map, scaleNow) {
  const perScreenPx = map.groundPx / scaleNow;
  const len = niceLength(perScreenPx * SCALE_BAR_PX);
  ui.bar.style.width = `${len / perScreenPx}px`;
  ui.barLabel.textContent = length(len, map.metric);
}

// the ground coordinates under the cursor, to about one screen pixel
function followCursor(ui, pz, map) {
  ui.viewport.addEventListener("pointermove", (ev) => {
    const p = pz.local(ev);
    const { u, v } = pz.toTarget(p.x, p.y);
    const g = map.base && groundAt(map.survey, u, v, map.base.w, map.base.h);
    ui.where.hidden = !g;
    if (!g) return;
    const digits = Math.min(6, Math.max(0, Math.ceil(-Math.log10(map.groundPx / pz.scale() || 1))));
    const [ex, ny] = map.survey.frame?.georeferenced ? ["E", "N"] : ["x", "y"];
    ui.where.textContent = `${ex} ${g.x.toFixed(digits)}  ${ny} ${g.y.toFixed(digits)}${map.metric ? " m" : ""}`;
  });
  ui.viewport.addEventListener("pointerleave", () => { ui.where.hidden = true; });
}

// Show one layer's preview, keeping the view. The first one shown sets the box every layer is drawn into (one
// footprint: a coarser hillshade is stretched to it). Picks overtaken by a later one give way.
function layerSwitch(ui, pz, map, io) {
  const blobs = new Map(); // path -> Promise<blob: URL>
  const blobUrl = (path) => {
    if (!blobs.has(path)) blobs.set(path, io.fetchBlob(path).then((b) => io.track(URL.createObjectURL(b))));
    return blobs.get(path);
  };
  let turn = 0;
  return async function pick(key) {
    const [, label, path] = LAYERS.find(([k]) => k === key);
    const mine = ++turn;
    const src = await blobUrl(path);
    if (mine !== turn) return;
    ui.img.src = src;
    Object.assign(ui.img.dataset, { layer: key, path });
    ui.img.alt = `survey map, ${label}`;
    await ui.img.decode();
    if (!map.base) {
      map.base = { w: ui.img.naturalWidth, h: ui.img.naturalHeight };
      map.groundPx = groundPerPixel(map.survey, map.base.w);
      ui.scale.hidden = !map.groundPx;
      pz.setSize(map.base.w, map.base.h);
      ui.viewport.dataset.ready = "";
    }
    if (mine === turn) ui.viewport.dataset.shown = path; // this layer is on screen, placed (tests wait for it)
  };
}

function layerChoices(ui, products, pick) {
  const inputs = LAYERS.map(([key, label]) => {
    const present = products.layers.some(([k]) => k === key);
    const input = el("input", { type: "radio", name: "smap-layer", value: key, disabled: !present });
    input.addEventListener("change",
      () => pick(key).catch((e) => message(ui.why, `Could not show ${label}: ${errorText(e)}`)));
    return [input, el("label", { class: "inline", title: present ? "" : "not made for this job" }, input, label)];
  });
  ui.layers.replaceChildren(...inputs.map(([, label]) => label));
  return inputs.map(([input]) => input);
}

// Build the map into `root` (emptied first) and show its first layer. Returns {dispose} (drops its observers).
// io: fetchJson(path), fetchBlob(path) (artifacts, with the key), track(blobUrl), download(path, statusNode).
export async function showSurveyMap(root, products, io) {
  const ui = frame(root);
  const map = { survey: {}, metric: false, base: null, groundPx: null };
  const pz = panZoom(ui.viewport, ui.img, { onChange: ({ scale }) => map.groundPx && drawScaleBar(ui, map, scale) });
  const handle = { dispose: () => pz.dispose() };
  zoomButtons(ui, pz);
  followCursor(ui, pz, map);
  try {
    map.survey = await readSurvey(products, io);
  } catch (e) {
    message(ui.why, `Could not read the survey's numbers: ${errorText(e)}`);
  }
  map.metric = isMetric(map.survey);
  const status = el("span", { class: "muted", role: "status" });
  ui.side.append(factList(map.survey), ...notes(map.survey).map((n) => el("p", { class: "hint" }, n)),
    el("h3", {}, "Downloads"), fileList(products, io, status), status);
  const pick = layerSwitch(ui, pz, map, io);
  const inputs = layerChoices(ui, products, pick);
  if (!products.layers.length) {
    message(ui.why, "No map previews were made for this job; the files are below.");
    return handle;
  }
  const has = (key) => products.layers.some(([k]) => k === key);
  if (!has("dewatered") && has("water")) message(ui.why, await whyNoDewatered(products, io));
  const first = inputs.find((i) => !i.disabled);
  first.checked = true;
  await pick(first.value);
  return handle;
}

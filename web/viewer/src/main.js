// The dashboard's 3D viewer: window.DualphysViewer.mount(container, {splatUrl, format, headers, camerasUrl}).
//
// The splat file (and cameras.json) are fetched here, with the caller's headers (the artifacts need the Bearer
// key), and the bytes handed to Spark; nothing ever goes into a URL. The scene is shown in the PLY's own frame
// (COLMAP world: the training cameras look down +z with y pointing down in the image); the three.js camera is
// placed on one of those cameras with its up vector set to the cameras' mean "image up", so the first view is
// upright and in frame.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import { cameraFrustums, startPose } from "./cameras.js";
import { backgroundColour, installDisplay } from "./water.js";

export const VERSION = "0.1.0";

async function fetchBytes(url, headers) {
  // credentials "omit": the key travels only in the Authorization header the caller gave us. "no-store": the
  // browser's cache is keyed by URL, not by key, so a cached artifact could be shown to the next key signed in.
  const res = await fetch(url, { headers: headers || {}, credentials: "omit", cache: "no-store" });
  if (!res.ok) throw new Error(`could not load ${url}: HTTP ${res.status}`);
  return new Uint8Array(await res.arrayBuffer());
}

async function fetchJson(url, headers) {
  return JSON.parse(new TextDecoder().decode(await fetchBytes(url, headers)));
}

function showMessage(container, text) {
  const box = document.createElement("div");
  box.className = "dualphys-viewer-message";
  box.textContent = text;
  box.style.cssText = "position:absolute;left:8px;top:8px;padding:4px 8px;background:#0008;color:#fff;" +
    "font:13px sans-serif;border-radius:4px;pointer-events:none";
  container.appendChild(box);
  return box;
}

function waterToggle(container, onChange) {
  const label = document.createElement("label");
  label.className = "dualphys-viewer-water";
  label.title = "Show the scene through the water the job measured (its homogeneous medium), or restored";
  label.style.cssText = "position:absolute;right:8px;top:8px;padding:4px 8px;background:#0008;color:#fff;" +
    "font:13px sans-serif;border-radius:4px;cursor:pointer;user-select:none";
  const box = document.createElement("input");
  box.type = "checkbox";
  box.style.marginRight = "4px";
  box.addEventListener("change", () => onChange(box.checked));
  label.append(box, "With water");
  container.appendChild(label);
  return label;
}

/**
 * Show a Gaussian-splat file in `container` (which should have a size; the canvas fills it).
 * @param {HTMLElement} container
 * @param {{splatUrl: string, format?: 'ply'|'spz', headers?: object, camerasUrl?: string|null}} opts
 * @returns {Promise<{dispose(): void, camera: THREE.PerspectiveCamera, controls: OrbitControls,
 *   numSplats: number, numCameras: number, hasWater: boolean, setWater(on: boolean): boolean,
 *   render(): void, frames: number}>}
 */
export async function mount(container, opts) {
  const { splatUrl, format = "ply", headers = {}, camerasUrl = null } = opts || {};
  if (!splatUrl) throw new Error("DualphysViewer.mount: splatUrl is required");
  if (format !== "ply" && format !== "spz") throw new Error(`DualphysViewer.mount: unknown format ${format}`);
  container.dataset.viewerState = "loading";
  if (getComputedStyle(container).position === "static") container.style.position = "relative";
  const status = showMessage(container, "Loading the reconstruction…");

  let renderer = null;
  let frame = 0;
  let render = () => {};
  let disposed = false;
  try {
    const [bytes, cams] = await Promise.all([
      fetchBytes(splatUrl, headers),
      camerasUrl ? fetchJson(camerasUrl, headers) : Promise.resolve(null),
    ]);

    const width = Math.max(container.clientWidth, 1);
    const height = Math.max(container.clientHeight, 1);
    // preserveDrawingBuffer: the page (and the tests) can read the canvas back as an image.
    renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setSize(width, height);
    renderer.setClearColor(0x101820, 1);
    renderer.domElement.style.display = "block";
    container.appendChild(renderer.domElement);

    const scene = new THREE.Scene();
    // Frames on demand, not a loop: without a GPU (software WebGL) every frame costs the CPU ~0.7 s for the demo's
    // 24k Gaussians, and an idle tab would keep a core busy. Spark calls onDirty when its sort or an update of the
    // splats (the water switch) finishes; the controls and the resize ask for the rest.
    let pending = false;
    const requestRender = () => {
      if (pending || disposed) return;
      pending = true;
      frame = requestAnimationFrame(() => {
        pending = false;
        if (!disposed) render();
      });
    };
    scene.add(new SparkRenderer({ renderer, onDirty: requestRender }));
    const mesh = new SplatMesh({ fileBytes: bytes, fileType: format });
    // SPZ stores RUB axes (x right, y up, z back; the format's definition, and what pipeline/splat/spz.py
    // writes), Spark shows them as stored; the PLY and cameras.json are RDF (COLMAP). A 180° turn about x maps one
    // onto the other.
    if (format === "spz") mesh.quaternion.set(1, 0, 0, 0);
    await mesh.initialized;
    scene.add(mesh);
    const display = cams ? cams.display : null;
    const setWaterColours = installDisplay(mesh, display);
    let withWater = false;
    const setWater = (flag) => {
      if (!setWaterColours) return false;
      withWater = Boolean(flag);
      setWaterColours(withWater);
      renderer.setClearColor(backgroundColour(display, withWater), 1);
      requestRender();
      if (toggle) toggle.querySelector("input").checked = withWater;
      return withWater;
    };
    let toggle = null;
    if (setWaterColours) {
      toggle = waterToggle(container, (flag) => setWater(flag));
    }

    mesh.updateMatrixWorld();
    const box = mesh.getBoundingBox(true).clone().applyMatrix4(mesh.matrixWorld); // in the world (RDF) frame
    const pose = startPose(cams, box);
    const camera = new THREE.PerspectiveCamera(pose.fovY, width / height, pose.near, pose.far);
    camera.up.copy(pose.up);
    camera.position.copy(pose.position);
    camera.lookAt(pose.target);

    let numCameras = 0;
    if (cams && cams.cameras && cams.cameras.length) {
      const frustums = cameraFrustums(cams.cameras, pose.markerSize);
      scene.add(frustums);
      numCameras = cams.cameras.length;
    }

    const controls = new OrbitControls(camera, renderer.domElement);
    controls.target.copy(pose.target);
    controls.enableDamping = false;
    controls.screenSpacePanning = true;
    controls.update();

    controls.addEventListener("change", requestRender);
    let frames = 0;
    render = () => {
      frames += 1;
      renderer.render(scene, camera);
    };
    requestRender();

    const resize = new ResizeObserver(() => {
      const w = Math.max(container.clientWidth, 1);
      const h = Math.max(container.clientHeight, 1);
      renderer.setSize(w, h);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
      requestRender();
    });
    resize.observe(container);

    status.remove();
    container.dataset.viewerState = "ready";
    return {
      camera,
      controls,
      render,
      get frames() {
        return frames; // frames drawn so far (none while nothing changes)
      },
      numCameras,
      hasWater: Boolean(setWaterColours),
      setWater,
      numSplats: (mesh.packedSplats || mesh.extSplats || {}).numSplats || 0,
      dispose() {
        disposed = true;
        cancelAnimationFrame(frame);
        resize.disconnect();
        if (toggle) toggle.remove();
        controls.dispose();
        mesh.dispose();
        renderer.dispose();
        renderer.domElement.remove();
        delete container.dataset.viewerState;
      },
    };
  } catch (err) {
    disposed = true;
    cancelAnimationFrame(frame);
    if (renderer) {
      renderer.dispose();
      renderer.domElement.remove();
    }
    status.textContent = `The 3D view could not be shown: ${err.message || err}`;
    container.dataset.viewerState = "error";
    throw err;
  }
}

window.DualphysViewer = { mount, VERSION };

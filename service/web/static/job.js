// One job: state and progress (polled until it ends), stages with their timings, the log tail, and once results
// exist the report, the gallery, the water maps, the survey map (surveymap.js; only for jobs with survey
// products), the 3D view and the downloads. Every file is fetched with the key and shown through a blob: URL.
import { ApiError, authHeaders, getBlob, getJson, postJson, request } from "./api.js";
import { showSurveyMap, surveyProducts } from "./surveymap.js";
import { $, $$, bytes, el, errorText, message, saveBlob, seconds, show, stateBadge, TERMINAL } from "./ui.js";

const POLL_MS = 1500;
const LOG_TAIL_BYTES = 32 << 10;
const LOG_KEEP_CHARS = 64 << 10;
const GALLERY_MAX = 24;
const SHOWABLE = new Set(["image/png", "image/jpeg", "image/webp", "image/gif"]);
const MAPS = [["with_water", "with water"], ["restored", "restored"], ["attenuation", "attenuation A"],
  ["backscatter", "backscatter B"], ["depth", "depth"]];

let job = null;         // the id shown
let timer = null;
let logOffset = null;
let artifacts = null;   // the listing, once the job is done
let loaded = new Set(); // tabs whose content was built
let blobUrls = [];
let viewer = null;
let surveyMap = null;   // the survey map's handle ({dispose}) once built
let go = () => {};

function url(path) { return `/v1/jobs/${encodeURIComponent(job)}${path}`; }

function track(blobUrl) { blobUrls.push(blobUrl); return blobUrl; }

// An <img> whose file is fetched with the key and shown through a blob: URL; `pending` collects the loads so a
// view can wait for all of them (they run in parallel).
function blobImage(path, alt, pending) {
  const img = el("img", { alt, "data-path": path });
  pending.push(getBlob(url(`/artifacts/${path}`))
    .then((blob) => { img.src = track(URL.createObjectURL(blob)); })
    .catch((e) => { img.alt = `${alt}: ${errorText(e)}`; }));
  return img;
}

function renderStatus(s) {
  $("#job-title").replaceChildren("Job ", el("span", { class: "mono" }, s.id));
  $("#job-state").replaceWith(Object.assign(stateBadge(s.state), { id: "job-state" }));
  $("#job-progress").value = s.progress;
  $("#job-percent").textContent = `${s.progress.toFixed(1)}%`;
  $("#job-message").textContent = s.message || "";
  $("#job-summary").dataset.state = s.state;
  message($("#job-failure"), s.error ? `${s.error.stage || "job"} failed: ${s.error.message} (${s.error.code})` : "");
  const active = s.state === "queued" || s.state === "running" || s.state === "cancelling";
  show($("#job-cancel"), active);
  show($("#job-retry"), s.state === "failed" || s.state === "cancelled");
  show($("#job-delete"), !active);
  $("#stages-body").replaceChildren(...s.stages.map((st) => el("tr", { "data-stage": st.name },
    el("td", {}, st.name),
    el("td", {}, stateBadge(st.skipped ? "skipped" : st.status)),
    el("td", { class: "num" }, seconds(st.seconds)),
    el("td", { class: "num" }, st.attempts || ""))));
}

async function tailLog() {
  const pre = $("#job-log");
  if (logOffset === null) {
    const head = await getJson(url(`/log?offset=0&limit=1`));
    logOffset = Math.max(0, head.size - LOG_TAIL_BYTES);
  }
  for (let i = 0; i < 8; i++) {
    const part = await getJson(url(`/log?offset=${logOffset}`));
    if (part.text) {
      const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
      pre.textContent = (pre.textContent + part.text).slice(-LOG_KEEP_CHARS);
      if (atEnd) pre.scrollTop = pre.scrollHeight;
    }
    if (part.next_offset === logOffset) break;
    logOffset = part.next_offset;
  }
}

async function poll() {
  const id = job;
  try {
    const s = await getJson(url(""));
    if (id !== job) return;
    show($("#job-summary"), true);
    show($("#job-body"), true);
    message($("#job-error"), "");
    renderStatus(s);
    await tailLog();
    if (s.state === "done" && artifacts === null) await loadArtifacts();
    if (TERMINAL.has(s.state)) { timer = null; return; }
  } catch (e) {
    if (id !== job) return;
    if (e instanceof ApiError && e.status === 404) {
      show($("#job-summary"), false);
      show($("#job-body"), false);
      $("#job-title").replaceChildren("Job not found");
      message($("#job-error"), `No job ${id} here: it does not exist, was deleted, or belongs to another API key.`);
      timer = null;
      return;
    }
    message($("#job-error"), `Could not load the job: ${errorText(e)}`);
  }
  if (timer !== null) timer = setTimeout(poll, POLL_MS);
}

async function loadArtifacts() {
  artifacts = (await getJson(url("/artifacts"))).artifacts;
  renderDownloads();
  show($(".tabs [data-tab=survey]"), surveyProducts(artifacts) !== null);
  const tab = $(".tabs .active")?.dataset.tab;
  if (tab) openTab(tab);
}

function byPrefix(prefix) {
  return (artifacts || []).filter((a) => a.path.startsWith(prefix) && SHOWABLE.has(a.media_type));
}

function renderDownloads() {
  $("#files-body").replaceChildren(...artifacts.map((a) => el("tr", {},
    el("td", { class: "mono" }, a.path),
    el("td", { class: "num" }, bytes(a.size)),
    el("td", { class: "mono muted", title: a.sha256 }, a.sha256.slice(0, 12)),
    el("td", {}, el("button", { type: "button", class: "ghost small", onclick: () => download(a.path) }, "download")))));
}

async function download(path, msg = $("#download-msg")) {
  msg.textContent = `Downloading ${path}…`;
  try {
    const name = path === "bundle" ? `${job}.zip` : path.split("/").pop();
    saveBlob(await getBlob(url(path === "bundle" ? "/bundle" : `/artifacts/${path}`)), name);
    msg.textContent = `Saved ${name}.`;
  } catch (e) {
    msg.textContent = `Download failed: ${errorText(e)}`;
  }
}

async function showReport() {
  const report = (artifacts || []).find((a) => a.path.endsWith("report.html"));
  if (!report) return;
  const html = await (await request(url(`/artifacts/${report.path}`))).text();
  const frame = $("#report-frame");
  frame.srcdoc = html;  // sandbox="" : no scripts, its own opaque origin
  show(frame, true);
  show($("#report-msg"), false);
}

// A preview (small JPEG the service makes) of a photo or of its restored version, fetched with the key.
function previewImage(kind, stem, alt, pending) {
  const img = el("img", { alt, "data-preview": `${kind}/${stem}` });
  pending.push(getBlob(url(`/previews/${kind}/${encodeURIComponent(stem)}`))
    .then((blob) => { img.src = track(URL.createObjectURL(blob)); })
    .catch((e) => { img.alt = `${alt}: ${errorText(e)}`; }));
  return img;
}

// Your photos as taken | de-watered (previews), then the model's own views: with water | restored.
async function showGallery() {
  const photos = byPrefix("output/restored/");
  const views = byPrefix("output/renders/with_water/");
  const restored = new Map(byPrefix("output/renders/restored/").map((a) => [a.path.split("/").pop(), a.path]));
  const pending = [];
  message($("#gallery-msg"), views.length || photos.length ? "Loading the views…" : "This job has no restored photos.");
  $("#gallery").replaceChildren(...photos.slice(0, GALLERY_MAX).map((a) => {
    const name = a.path.split("/").pop();
    const stem = name.replace(/\.[^.]*$/, "");
    return el("figure", { class: "pair" },
      previewImage("original", stem, `${name} as taken`, pending),
      previewImage("restored", stem, `${name} restored`, pending),
      el("figcaption", {}, `${name}: as taken | restored (full size in Downloads)`));
  }));
  show($("#photos-title"), views.length > 0);
  $("#photos").replaceChildren(...views.slice(0, GALLERY_MAX).map((a) => {
    const name = a.path.split("/").pop();
    return el("figure", { class: "pair" },
      blobImage(a.path, `${name} with water`, pending),
      restored.has(name) ? blobImage(restored.get(name), `${name} restored`, pending) : null,
      el("figcaption", {}, `${name}: with water | restored`));
  }));
  await Promise.all(pending);
  if (views.length || photos.length) message($("#gallery-msg"), "");
}

async function showMaps() {
  const select = $("#maps-view");
  const names = byPrefix("output/renders/with_water/").map((a) => a.path.split("/").pop());
  if (!select.options.length) {
    select.replaceChildren(...names.map((n) => el("option", { value: n }, n)));
    select.onchange = () => showMaps();
  }
  const name = select.value;
  const pending = [];
  const figures = MAPS.map(([folder, label]) => [`output/renders/${folder}/${name}`, label])
    .filter(([path]) => artifacts.some((a) => a.path === path))
    .map(([path, label]) => el("figure", {}, blobImage(path, label, pending), el("figcaption", {}, label)));
  $("#maps").replaceChildren(...figures);
  message($("#maps-msg"), figures.length ? "" : "This job wrote no water maps (mode 3dgs models no water).");
  await Promise.all(pending);
}

function loadViewerScript() {
  if (window.DualphysViewer) return Promise.resolve(window.DualphysViewer);
  return new Promise((resolve, reject) => {
    const s = el("script", { src: "/static/viewer/viewer.js" });
    s.onload = () => (window.DualphysViewer ? resolve(window.DualphysViewer) : reject(new Error("no viewer")));
    s.onerror = () => { s.remove(); reject(new Error("not installed")); };
    document.head.append(s);
  });
}

async function showViewer() {
  const msg = $("#viewer-msg");
  const pick = (suffix) => (artifacts || []).find((a) => a.path.endsWith(suffix));
  const splat = pick("reconstruction.spz") || pick("reconstruction.ply");
  if (!splat) { msg.textContent = "This job has no reconstruction to show."; return; }
  let lib;
  try {
    lib = await loadViewerScript();
  } catch {
    msg.textContent = "The 3D viewer is not part of this installation; download reconstruction.ply instead.";
    return;
  }
  msg.textContent = "Loading the reconstruction…";
  const cameras = pick("cameras.json");
  try {
    viewer = await lib.mount($("#viewer"), {
      splatUrl: splat.url || url(`/artifacts/${splat.path}`),
      format: splat.path.endsWith(".spz") ? "spz" : "ply",
      headers: authHeaders(),
      camerasUrl: cameras ? cameras.url || url(`/artifacts/${cameras.path}`) : null,
    });
    msg.textContent = "Drag to orbit, right-drag to pan, scroll to zoom.";
  } catch (e) {
    msg.textContent = `The 3D view failed: ${errorText(e)}`;
  }
}

async function showSurvey() {
  const id = job;
  const msg = $("#survey-map-msg");
  const products = surveyProducts(artifacts);
  if (!products) { message(msg, "This job made no survey products."); return; }
  const artifact = (path) => url(`/artifacts/${path}`);
  const map = await showSurveyMap($("#survey-map"), products, {
    fetchJson: (path) => getJson(artifact(path)), fetchBlob: (path) => getBlob(artifact(path)), track, download,
  });
  if (id !== job) { map.dispose(); return; }
  surveyMap = map;
  message(msg, "");
}

const TABS = { report: showReport, gallery: showGallery, maps: showMaps, survey: showSurvey, viewer: showViewer };

function openTab(name) {
  for (const b of $$(".tabs [data-tab]")) b.classList.toggle("active", b.dataset.tab === name);
  for (const p of $$("[data-pane]")) show(p, p.dataset.pane === name);
  if (artifacts && TABS[name] && !loaded.has(name)) {
    loaded.add(name);
    TABS[name]().catch((e) => message($("#job-error"), `Could not show ${name}: ${errorText(e)}`));
  }
}

async function act(what) {
  try {
    if (what === "delete") {
      if (!confirm(`Delete job ${job} and all its files?`)) return;
      await request(url(""), { method: "DELETE" });
      go("/");
      return;
    }
    const s = await postJson(url(`/${what}`));
    renderStatus(s);
    if (timer === null) { timer = 0; poll(); }
  } catch (e) {
    message($("#job-error"), `${what} refused: ${errorText(e)}`);
  }
}

let wired = false;
function wire() {
  if (wired) return;
  wired = true;
  for (const b of $$(".tabs [data-tab]")) b.addEventListener("click", () => openTab(b.dataset.tab));
  $("#job-cancel").addEventListener("click", () => act("cancel"));
  $("#job-retry").addEventListener("click", () => act("retry"));
  $("#job-delete").addEventListener("click", () => act("delete"));
  $("#bundle").addEventListener("click", () => download("bundle"));
}

function reset() {
  clearTimeout(timer);
  timer = null;
  if (viewer) { try { viewer.dispose(); } catch { /* already gone */ } viewer = null; }
  if (surveyMap) { surveyMap.dispose(); surveyMap = null; }
  for (const u of blobUrls) URL.revokeObjectURL(u);
  blobUrls = [];
  artifacts = null;
  loaded = new Set();
  logOffset = null;
  for (const id of ["#job-log", "#stages-body", "#gallery", "#photos", "#maps", "#maps-view", "#files-body", "#viewer",
    "#survey-map"]) {
    $(id).replaceChildren();
  }
  const frame = $("#report-frame");
  frame.removeAttribute("srcdoc");
  show(frame, false);
  show($("#report-msg"), true);
  show($(".tabs [data-tab=survey]"), false);
  message($("#survey-map-msg"), "Loading the survey map…");
  message($("#job-error"), "");
  show($("#job-summary"), false);
  show($("#job-body"), false);
  $("#job-title").textContent = "Job";
}

export const jobView = {
  enter({ id }, navigate) {
    go = navigate;
    wire();
    reset();
    job = id;
    openTab("overview");
    timer = 0;
    poll();
  },
  leave() {
    reset();
    job = null;
  },
};

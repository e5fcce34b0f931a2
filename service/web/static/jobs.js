// The job list (polled while shown) and the upload form.
import { getJson, uploadJob } from "./api.js";
import { $, bytes, el, errorText, message, show, stateBadge, when } from "./ui.js";
import { storeZip } from "./zip.js";

const POLL_MS = 1500;
let timer = null;
let go = () => {};

function shortId(id) { return id.length > 14 ? `${id.slice(0, 12)}…` : id; }

function row(job) {
  const href = `/jobs/${encodeURIComponent(job.id)}`;
  const pct = Math.round(job.progress);
  return el("tr", { "data-job": job.id, "data-state": job.state },
    el("td", {}, el("a", { href, "data-link": true, title: job.id, class: "mono" }, shortId(job.id))),
    el("td", {}, job.source?.filename || job.source?.set_name || job.survey_id || ""),
    el("td", {}, stateBadge(job.state)),
    el("td", {}, el("progress", { max: 100, value: job.progress }), el("span", { class: "pct" }, ` ${pct}%`)),
    el("td", { class: "muted" }, job.stage || ""),
    el("td", { class: "muted" }, when(job.created_at)));
}

async function refresh() {
  try {
    const list = await getJson("/v1/jobs?limit=100");
    $("#jobs-body").replaceChildren(...list.jobs.map(row));
    show($("#jobs-empty"), list.jobs.length === 0);
    message($("#jobs-error"), "");
  } catch (e) {
    message($("#jobs-error"), `Could not list jobs: ${errorText(e)}`);
  }
}

function schedule() {
  timer = setTimeout(async () => { await refresh(); if (timer !== null) schedule(); }, POLL_MS);
}

function picked() {
  const archive = $("#upload-archive").files[0];
  if (archive) return { archive };
  const files = [...$("#upload-files").files, ...$("#upload-folder").files];
  return files.length ? { files } : null;
}

function describePick() {
  const p = picked();
  let text = "";
  if (p?.archive) text = `${p.archive.name} (${bytes(p.archive.size)})`;
  else if (p?.files) text = `${p.files.length} files (${bytes(p.files.reduce((s, f) => s + f.size, 0))}), zipped before upload`;
  $("#upload-picked").textContent = text;
}

function optionFields(form) {
  const fields = {};
  for (const input of form.querySelectorAll(".options [name]")) {
    const v = input.value.trim();
    if (v !== "") fields[input.name] = v;
  }
  return fields;
}

async function submit(ev) {
  ev.preventDefault();
  const msg = $("#upload-msg");
  const bar = $("#upload-progress");
  const p = picked();
  if (!p) { msg.textContent = "Pick an archive, some images or a folder first."; return; }
  const button = $("#upload-submit");
  button.disabled = true;
  try {
    let blob = p.archive;
    let name = p.archive?.name;
    if (!blob) {
      msg.textContent = "Packing the files…";
      const entries = p.files.map((f) => ({ name: f.webkitRelativePath || f.name, file: f }));
      blob = await storeZip(entries, (i, n) => { msg.textContent = `Packing the files… ${i}/${n}`; });
      name = `${(p.files[0].webkitRelativePath || "images").split("/")[0] || "images"}.zip`;
    }
    show(bar, true);
    bar.value = 0;
    const job = await uploadJob(blob, name, optionFields(ev.target), (done, total) => {
      bar.value = (100 * done) / total;
      msg.textContent = done < total ? `Uploading ${bytes(done)} of ${bytes(total)}` : "Checking the images…";
    });
    msg.textContent = `Job ${job.id} started.`;
    ev.target.reset();
    describePick();
    await refresh();
  } catch (e) {
    msg.textContent = `Upload refused: ${errorText(e)}`;
  } finally {
    button.disabled = false;
    show(bar, false);
  }
}

function openJob(ev) {
  ev.preventDefault();
  const id = $("#open-job-id").value.trim();
  if (id) go(`/jobs/${encodeURIComponent(id)}`);
}

let wired = false;
function wire() {
  if (wired) return;
  wired = true;
  $("#upload-form").addEventListener("submit", submit);
  $("#open-job").addEventListener("submit", openJob);
  for (const id of ["#upload-archive", "#upload-files", "#upload-folder"]) {
    $(id).addEventListener("change", (ev) => {
      // one source at a time: picking one clears the others
      for (const other of ["#upload-archive", "#upload-files", "#upload-folder"]) if (other !== id) $(other).value = "";
      describePick(ev);
    });
  }
}

export const jobsView = {
  enter(_params, navigate) {
    go = navigate;
    wire();
    refresh();
    schedule();
  },
  leave() {
    clearTimeout(timer);
    timer = null;
  },
};

// Survey folders: register one, scan now, the sets found (submitted and waiting) and their jobs.
import { getJson, postJson, request } from "./api.js";
import { $, el, errorText, message, show, stateBadge, when } from "./ui.js";

const POLL_MS = 3000;
let timer = null;

async function card(s) {
  const jobs = await getJson(`/v1/jobs?survey=${encodeURIComponent(s.id)}&limit=50`).catch(() => ({ jobs: [] }));
  const state = new Map(jobs.jobs.map((j) => [j.id, j]));
  const scan = el("button", { type: "button", class: "ghost small" }, "Scan now");
  const drop = el("button", { type: "button", class: "danger small" }, "Stop scanning");
  const status = el("span", { class: "muted", role: "status" });
  scan.onclick = async () => {
    try { await postJson(`/v1/surveys/${encodeURIComponent(s.id)}/scan`); status.textContent = "scan queued"; }
    catch (e) { status.textContent = errorText(e); }
  };
  drop.onclick = async () => {
    if (!confirm(`Stop scanning ${s.name}? Its jobs stay.`)) return;
    try { await request(`/v1/surveys/${encodeURIComponent(s.id)}`, { method: "DELETE" }); refresh(); }
    catch (e) { status.textContent = errorText(e); }
  };
  const sets = s.sets.map((set) => {
    const j = state.get(set.job_id);
    return el("tr", {},
      el("td", {}, set.name), el("td", { class: "num" }, set.images),
      el("td", {}, el("a", { href: `/jobs/${encodeURIComponent(set.job_id)}`, "data-link": true, class: "mono" }, set.job_id)),
      el("td", {}, j ? stateBadge(j.state) : el("span", { class: "muted" }, "deleted")),
      el("td", { class: "muted" }, when(set.submitted_at)));
  });
  const waiting = s.waiting.map((w) => el("li", {}, `${w.name}: ${w.images} images, ${w.reason}`));
  return el("div", { class: "card", "data-survey": s.id },
    el("div", { class: "row between" },
      el("h3", {}, s.name, " ", el("span", { class: "muted mono" }, s.path)),
      el("div", { class: "row" }, status, scan, s.origin === "api" ? drop : null)),
    el("p", { class: "muted" }, `every ${s.interval_s} s · ${s.scans} scan${s.scans === 1 ? "" : "s"} · last ${when(s.last_scan_at) || "never"}`),
    s.last_error ? el("p", { class: "error" }, `last scan: ${s.last_error} (${s.last_error_code || "error"})`) : null,
    sets.length
      ? el("table", {}, el("thead", {}, el("tr", {}, ...["set", "images", "job", "state", "submitted"].map((h) => el("th", {}, h)))),
        el("tbody", {}, sets))
      : el("p", { class: "muted" }, "No sets submitted yet."),
    waiting.length ? el("div", {}, el("h4", {}, "Waiting"), el("ul", {}, waiting)) : null);
}

async function refresh() {
  try {
    const { surveys } = await getJson("/v1/surveys");
    $("#surveys-list").replaceChildren(...(await Promise.all(surveys.map(card))));
    show($("#surveys-empty"), surveys.length === 0);
    message($("#surveys-error"), "");
  } catch (e) {
    message($("#surveys-error"), `Could not list surveys: ${errorText(e)}`);
  }
}

async function register(ev) {
  ev.preventDefault();
  const f = new FormData(ev.target);
  const msg = $("#survey-msg");
  const body = { path: f.get("path").trim(), interval_s: Number(f.get("interval_s")) };
  if (f.get("name").trim()) body.name = f.get("name").trim();
  if (f.get("callback_url").trim()) body.callback_url = f.get("callback_url").trim();
  const opts = f.get("options").trim();
  if (opts) {
    try { body.options = JSON.parse(opts); } catch { msg.textContent = "job options: not valid JSON"; return; }
  }
  try {
    const s = await postJson("/v1/surveys", body);
    msg.textContent = `Registered ${s.name}.`;
    ev.target.reset();
    refresh();
  } catch (e) {
    msg.textContent = `Refused: ${errorText(e)}`;
  }
}

let wired = false;

export const surveysView = {
  enter() {
    if (!wired) { wired = true; $("#survey-form").addEventListener("submit", register); }
    refresh();
    timer = setInterval(refresh, POLL_MS);
  },
  leave() {
    clearInterval(timer);
    timer = null;
  },
};

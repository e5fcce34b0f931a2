// The dashboard's entry point: sign-in, the client-side routes (/, /jobs/<id>, /surveys) and the view switch.
import { getJson, session, whenUnauthorized } from "./api.js";
import { jobView } from "./job.js";
import { jobsView } from "./jobs.js";
import { surveysView } from "./surveys.js";
import { $, $$, errorText, message, show } from "./ui.js";

const VIEWS = { jobs: jobsView, job: jobView, surveys: surveysView };
let current = null;

function route(path) {
  const m = path.match(/^\/jobs\/([^/]+)\/?$/);
  if (m) return ["job", { id: decodeURIComponent(m[1]) }];
  if (path.startsWith("/surveys")) return ["surveys", {}];
  return ["jobs", {}];
}

export function navigate(path, replace = false) {
  if (replace) history.replaceState(null, "", path);
  else if (path !== location.pathname) history.pushState(null, "", path);
  render();
}

function leave() {
  if (current) VIEWS[current].leave();
  current = null;
}

function render() {
  leave();
  const signedIn = Boolean(session.key);
  show($("#view-signin"), !signedIn);
  show($("#nav"), signedIn);
  show($("#signout"), signedIn);
  for (const name of ["jobs", "job", "surveys"]) show($(`#view-${name}`), false);
  if (!signedIn) {
    $("#signin-key").focus();
    return;
  }
  const [name, params] = route(location.pathname);
  for (const a of $$("[data-nav]")) a.classList.toggle("active", a.dataset.nav === (name === "job" ? "jobs" : name));
  show($(`#view-${name}`), true);
  current = name;
  VIEWS[name].enter(params, navigate);
}

async function signIn(ev) {
  ev.preventDefault();
  const key = $("#signin-key").value.trim();
  const err = $("#signin-error");
  message(err, "");
  try {
    await getJson("/v1/jobs?limit=1", { key });
  } catch (e) {
    message(err, e.status === 401
      ? "This API key was not accepted. Check it and try again (the server said: " + e.message + ")."
      : `Could not reach the service: ${errorText(e)}`);
    return;
  }
  session.set(key);
  $("#signin-key").value = "";
  render();
}

function signOut(reason) {
  session.clear();
  leave();
  render();
  if (reason) message($("#signin-error"), reason);
}

function start() {
  $("#signin-form").addEventListener("submit", signIn);
  $("#signout").addEventListener("click", () => signOut());
  whenUnauthorized(() => signOut("Your API key is no longer accepted: sign in again."));
  // same-origin links with data-link switch views without a page load
  document.addEventListener("click", (ev) => {
    const a = ev.target.closest("a[data-link]");
    if (!a || ev.ctrlKey || ev.metaKey || ev.shiftKey || ev.button !== 0) return;
    ev.preventDefault();
    navigate(a.getAttribute("href"));
  });
  window.addEventListener("popstate", render);
  render();
}

start();

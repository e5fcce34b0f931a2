// The API client of the dashboard. The key lives in sessionStorage (this tab only, gone when it closes) and
// travels only in the Authorization header: no address the page requests ever carries it.

const KEY = "dualphys.apiKey";

export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

export const session = {
  get key() { return sessionStorage.getItem(KEY); },
  set(key) { sessionStorage.setItem(KEY, key); },
  clear() { sessionStorage.removeItem(KEY); },
};

let onUnauthorized = () => {};
export function whenUnauthorized(fn) { onUnauthorized = fn; }

export function authHeaders(key = session.key) {
  return key ? { Authorization: `Bearer ${key}` } : {};
}

async function errorOf(resp) {
  let code = `http_${resp.status}`;
  let message = resp.statusText || `HTTP ${resp.status}`;
  try {
    const body = await resp.json();
    if (body && body.error) ({ code, message } = body.error);
  } catch { /* not JSON: keep the status line */ }
  return new ApiError(resp.status, code, message);
}

// fetch with the key; JSON errors ({"error": {"code", "message"}}) become ApiError. `key` overrides the stored
// one (sign-in checks a key before keeping it).
export async function request(path, { method = "GET", body, headers = {}, key } = {}) {
  const resp = await fetch(path, {
    method, body, headers: { ...authHeaders(key ?? session.key), ...headers },
    credentials: "omit", cache: "no-store",
  });
  if (!resp.ok) {
    const err = await errorOf(resp);
    if (resp.status === 401 && key === undefined) onUnauthorized(err);
    throw err;
  }
  return resp;
}

export async function getJson(path, opts) {
  const resp = await request(path, opts);
  return resp.status === 204 ? null : resp.json();
}

export function postJson(path, data) {
  return getJson(path, {
    method: "POST", body: data === undefined ? undefined : JSON.stringify(data),
    headers: data === undefined ? {} : { "Content-Type": "application/json" },
  });
}

export async function getBlob(path) {
  return (await request(path)).blob();
}

// POST /v1/jobs as multipart (option fields first, then the archive) with upload progress, which fetch cannot
// report: XMLHttpRequest's upload events. Resolves with the job.
export function uploadJob(archive, filename, fields, onProgress) {
  const form = new FormData();
  for (const [k, v] of Object.entries(fields)) form.append(k, v);
  form.append("archive", archive, filename);
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/v1/jobs");
    for (const [k, v] of Object.entries(authHeaders())) xhr.setRequestHeader(k, v);
    xhr.responseType = "json";
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded, e.total); };
    xhr.onload = () => {
      const body = xhr.response;
      if (xhr.status >= 200 && xhr.status < 300) return resolve(body);
      const e = body && body.error ? body.error : { code: `http_${xhr.status}`, message: xhr.statusText };
      const err = new ApiError(xhr.status, e.code, e.message);
      if (xhr.status === 401) onUnauthorized(err);
      reject(err);
    };
    xhr.onerror = () => reject(new ApiError(0, "network_error", "the upload was interrupted (network error)"));
    xhr.send(form);
  });
}

// The REST API as promises. Every failure becomes an ApiError carrying the server's
// {"detail", "problems": [{location, message}]} so callers can show it where it belongs.
// Writes carry the operator's bearer token when the server needs one (set by setToken).

export class ApiError extends Error {
  constructor(status, detail, problems = []) {
    super(detail);
    this.status = status;
    this.detail = detail;
    this.problems = problems;
  }

  // The reason without the one located problem it quotes ("f.json: invalid telemetry: LOCATION: MESSAGE"),
  // for showing above the list of problems, where that one is listed already.
  get headline() {
    if (this.problems.length !== 1 || typeof this.detail !== "string") return this.detail;
    const only = `${this.problems[0].location}: ${this.problems[0].message}`;
    const rest = this.detail.endsWith(only) ? this.detail.slice(0, -only.length).replace(/[\s:]+$/, "") : "";
    return rest || this.detail;
  }
}

let token = "";
// The bearer token sent with every request (empty: none; a loopback server needs none).
export function setToken(value) { token = (value || "").trim(); }

function headers(extra = {}) {
  const h = { Accept: "application/json", ...extra };
  if (token) h.Authorization = `Bearer ${token}`;
  return h;
}

async function errorFrom(response) {
  let body = null;
  try { body = await response.json(); } catch { /* not JSON: fall back to the status text */ }
  const detail = (body && typeof body.detail === "string") ? body.detail
    : `${response.status} ${response.statusText || "error"}`;
  return new ApiError(response.status, detail, (body && Array.isArray(body.problems)) ? body.problems : []);
}

// request(...) resolves the parsed body; requestWithStatus(...) resolves {status, body}
// for the endpoints whose 200 and 201 mean different things (confirm, reject, upload).
export async function requestWithStatus(method, path, body) {
  const options = { method, headers: headers() };
  if (body !== undefined) {
    options.headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(path, options);
  } catch (err) {
    throw new ApiError(0, `the server cannot be reached (${err.message})`);
  }
  if (!response.ok) throw await errorFrom(response);
  return { status: response.status, body: await response.json() };
}

export async function request(method, path, body) {
  return (await requestWithStatus(method, path, body)).body;
}

export const get = (path) => request("GET", path);
export const put = (path, body) => request("PUT", path, body);
export const post = (path, body) => request("POST", path, body);

// Upload one file as multipart/form-data with progress (fetch has no upload progress).
// Resolves {status, body}; rejects with ApiError carrying the located problems.
export function uploadFile(file, onProgress, { search = false } = {}) {
  const form = new FormData();
  form.append("file", file, file.name);
  return uploadForm(search ? "/api/sequences?search=true" : "/api/sequences", form, onProgress);
}

// POST a multipart form with upload progress (fetch has none): resolves {status, body}; rejects with
// an ApiError carrying the server's located problems. Spot lists (uploadFile) and passes of frames
// (frames-upload.js) both go through here.
export function uploadForm(path, form, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", path);
    if (token) xhr.setRequestHeader("Authorization", `Bearer ${token}`);
    xhr.responseType = "json";
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
    xhr.upload.onload = () => onProgress(1);
    xhr.onerror = () => reject(new ApiError(0, "the upload failed: the server cannot be reached"));
    xhr.onload = () => {
      const body = xhr.response;
      if (xhr.status >= 200 && xhr.status < 300) {
        resolve({ status: xhr.status, body });
      } else {
        const detail = body && typeof body.detail === "string" ? body.detail : `${xhr.status} ${xhr.statusText}`;
        reject(new ApiError(xhr.status, detail, body && Array.isArray(body.problems) ? body.problems : []));
      }
    };
    xhr.send(form);
  });
}

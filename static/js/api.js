// The REST API as promises. Every failure becomes an ApiError carrying the server's
// {"detail", "problems": [{location, message}]} so callers can show it where it belongs.

export class ApiError extends Error {
  constructor(status, detail, problems = []) {
    super(detail);
    this.status = status;
    this.detail = detail;
    this.problems = problems;
  }
}

async function errorFrom(response) {
  let body = null;
  try { body = await response.json(); } catch { /* not JSON: fall back to the status text */ }
  const detail = (body && typeof body.detail === "string") ? body.detail
    : `${response.status} ${response.statusText || "error"}`;
  return new ApiError(response.status, detail, (body && Array.isArray(body.problems)) ? body.problems : []);
}

export async function request(method, path, body) {
  const options = { method, headers: { Accept: "application/json" } };
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
  return response.json();
}

export const get = (path) => request("GET", path);
export const put = (path, body) => request("PUT", path, body);
export const post = (path, body) => request("POST", path, body);

// Upload one file as multipart/form-data with progress (fetch has no upload progress).
// Resolves {status, body}; rejects with ApiError carrying the located problems.
export function uploadFile(file, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/api/sequences");
    xhr.responseType = "json";
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
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
    const form = new FormData();
    form.append("file", file, file.name);
    xhr.send(form);
  });
}

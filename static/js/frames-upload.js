// Full-frame images in the upload box: which dropped files are frames and which is their
// sidecar, and the one POST /api/frames request that sends them as one pass.
import { ApiError, uploadForm } from "./api.js";
import { $ } from "./dom.js";

// The server's image endings (app/frames/images.py ALL_SUFFIXES), lower case.
const FITS_SUFFIXES = [".fits", ".fit", ".fts", ".fits.gz", ".fit.gz"];
export const IMAGE_SUFFIXES = [...FITS_SUFFIXES, ".png", ".jpg", ".jpeg", ".tif", ".tiff"];
// A folder's sidecar, or a single image's <stem>.frames.json (as the CLI finds them).
export const FOLDER_SIDECAR = "frames.json";
export const SIDECAR_SUFFIX = ".frames.json";
export const FOV_MIN_DEG = 0.1, FOV_MAX_DEG = 120;

export const isImage = (file) => IMAGE_SUFFIXES.some((s) => file.name.toLowerCase().endsWith(s));
// FITS frames carry their times: a drop of them is a camera's pass even without a frames.json.
export const isFits = (file) => FITS_SUFFIXES.some((s) => file.name.toLowerCase().endsWith(s));
export const isSidecar = (file) => {
  const name = file.name.toLowerCase();
  return name === FOLDER_SIDECAR || name.endsWith(SIDECAR_SUFFIX);
};

// The text fields of the card for a pass: {fov_deg, spacecraft} as given (empty ones left out), or
// an ApiError located like the server's when the field of view is not a number in range.
export function frameFields() {
  const fov = $("upload-fov"), spacecraft = $("upload-spacecraft").value.trim();
  const fields = {};
  if (spacecraft) fields.spacecraft = spacecraft;
  const text = fov.value.trim();
  const value = Number(text);
  if (fov.validity.badInput || (text && !(value >= FOV_MIN_DEG && value <= FOV_MAX_DEG))) {
    return new ApiError(422, `the field of view must be a number from ${FOV_MIN_DEG} to ${FOV_MAX_DEG} degrees`,
      [{ location: "field of view", message: `must be ${FOV_MIN_DEG} to ${FOV_MAX_DEG} degrees` }]);
  }
  if (text) fields.fov_deg = text;
  return fields;
}

// POST /api/frames with the images as `files` parts, the sidecar (if any) and the text fields, with
// upload progress; search=true: the server searches a new pass after answering, as for spot lists.
export function uploadFrames(images, sidecar, fields, onProgress, { search = false } = {}) {
  const form = new FormData();
  for (const file of images) form.append("files", file, file.name);
  if (sidecar) form.append("sidecar", sidecar, sidecar.name);
  for (const [key, value] of Object.entries(fields)) form.append(key, value);
  return uploadForm(search ? "/api/frames?search=true" : "/api/frames", form, onProgress);
}

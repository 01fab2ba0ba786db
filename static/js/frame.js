// Frame panel: the frame of the snapshot the player shows, as kept at upload (stretched
// to 8 bits, at most 1024 pixels wide: GET /api/sequences/{id}/frames and .../frames/{i}.png),
// with what the detector made of it: the detections reported as sources (circles, labelled with
// their track as the player names it), the blobs it rejected (orange diamonds, the reason in the
// tooltip) and the camera's hot pixels (magenta squares). Wheel or +/- to zoom, drag to pan, Fit
// for the whole frame; a click on a detection takes its track in or out of the pattern, as a
// click in the player does. Annotated PNG downloads the frame annotated with the candidate shown
// (GET .../frames/{i}/annotated.png?rank=N). Telemetry strings only ever reach the page as text.
import * as api from "./api.js";
import { $, placeLabel, snapshotName, trackColour } from "./dom.js";
import { state } from "./state.js";

const MAX_ZOOM = 32;            // screen pixels per sensor pixel at most
const ZOOM_STEP = 1.5;          // one +/- press
const WHEEL_RATE = 0.0015;      // zoom factor per wheel delta unit: exp(-delta * rate)
const DRAG_THRESHOLD_PX = 4;    // a press that moves less than this is a click
const MAX_HEIGHT_PX = 620;      // the panel's canvas is never taller
const COLOURS = { rejected: "#ff922b", fainter: "#8b97a8", hot: "#f06595", untracked: "#dfe6ee", out: "#9aa4b2" };

// Why a blob is no source, as the operator reads it.
const REASONS = {
  hot_pixel: "hot pixel (one sharp pixel)", mapped_hot_pixel: "on a mapped hot pixel", elongated: "elongated (a trail)",
  extended: "extended (glare, Moon, limb, a treeline's edge)", not_brightest: "a star beyond the brightest reported", saturated: "saturated",
  edge: "cut by the frame's edge", border: "at the frame's border, no whole star",
  row: "in a row (text, a treeline, lights)", no_flux: "no light above the sky in its aperture",
};
const round1 = (v) => Math.round(v * 10) / 10;   // canvas positions as the page shows them to tests

export const reasonText = (reason) => String(reason).split("+").map((r) => REASONS[r] || r.replaceAll("_", " ")).join(", ");

export class FrameView {
  constructor({ onToggleTrack, onMessage }) {
    this.card = $("frame-card");
    this.canvas = $("frame-canvas");
    this.ctx = this.canvas.getContext("2d");
    this.tip = $("frame-tip");
    this.callbacks = { onToggleTrack, onMessage };
    this.detail = null;
    this.seqId = null;
    this.frames = null;          // snapshot -> frame info (null: not loaded, or no frames)
    this.images = new Map();     // url -> HTMLImageElement (previews never change)
    this.index = 0;
    this.zoom = 1;               // canvas pixels per sensor pixel
    this.ox = 0; this.oy = 0;    // canvas position of the sensor's top-left pixel edge
    this.fitted = true;          // the view follows the canvas size while nobody zoomed
    this.hits = [];
    this.drag = null;
    this.loading = 0;
    $("frame-zoom-in").addEventListener("click", () => this.zoomBy(ZOOM_STEP));
    $("frame-zoom-out").addEventListener("click", () => this.zoomBy(1 / ZOOM_STEP));
    $("frame-fit").addEventListener("click", () => { this.fit(); this.draw(); });
    $("frame-annotated").addEventListener("click", () => this.downloadAnnotated());
    for (const id of ["frame-show-detections", "frame-show-rejected", "frame-show-hot"]) {
      $(id).addEventListener("change", () => this.draw());
    }
    this.canvas.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
    this.canvas.addEventListener("mousedown", (e) => this.press(e));
    window.addEventListener("mousemove", (e) => this.move(e));
    window.addEventListener("mouseup", (e) => this.release(e));
    this.canvas.addEventListener("mouseleave", () => { this.tip.hidden = true; });
    new ResizeObserver(() => this.resize()).observe(this.card);
  }

  // A sequence (again: after a pattern edit the same sequence comes back with its new pattern).
  setSequence(detail) {
    const same = this.seqId === detail.id;
    this.detail = detail;
    this.inPattern = new Set(detail.pattern.points.filter((p) => p.track !== null).map((p) => p.track));
    if (same) { this.draw(); return; }
    this.seqId = detail.id;
    this.frames = null;
    this.fitted = true;
    const fromFrames = !!(detail.telemetry && detail.telemetry.frames);
    this.card.hidden = !fromFrames;
    this.note(fromFrames ? "Loading the frames..." : "");
    if (!fromFrames) return;
    const id = detail.id;
    api.get(`/api/sequences/${id}/frames`).then((doc) => {
      if (this.seqId !== id) return;
      this.frames = new Map(doc.frames.map((f) => [f.snapshot, f]));
      // What the reading said of the frames (turned upright, binned, trailed, a time zone), as plain text.
      const said = (detail.telemetry.frames.notes || []).join(" ");
      this.note(doc.frames.length ? said : "No frame images are kept of this sequence: its frames were uploaded " +
        "before previews were kept.");
      this.resize();
      this.show(this.index);
    }).catch((err) => {
      if (this.seqId !== id) return;
      this.note(`The frames cannot be loaded: ${err.detail || err.message}`);
    });
  }

  note(text) {
    $("frame-note").textContent = text;
    $("frame-note").hidden = !text;
  }

  // The snapshot the player shows.
  show(index) {
    this.index = index;
    const info = this.frames && this.frames.get(index);
    if (info && !this.images.has(info.url)) {
      const img = new Image();
      img.decoding = "async";
      img.onload = () => { if (this.current() === info) this.draw(); };
      img.onerror = () => { img.failed = true; if (this.current() === info) this.draw(); };
      img.src = info.url;
      this.images.set(info.url, img);
    }
    this.draw();
  }

  current() { return this.frames ? this.frames.get(this.index) ?? null : null; }

  // The frame shown, annotated with the candidate shown: fetched first, so that a sequence not searched
  // or a rank gone gives the server's sentence instead of a broken download.
  async downloadAnnotated() {
    const info = this.current(), rank = state.rank, id = this.seqId;
    if (!info) { this.callbacks.onMessage("No frame image is kept of this snapshot to annotate."); return; }
    if (!rank) { this.callbacks.onMessage("No candidate to annotate the frame with: search the sequence first."); return; }
    let response;
    try {
      response = await fetch(`/api/sequences/${id}/frames/${info.snapshot}/annotated.png?rank=${rank}`);
    } catch (err) {
      this.callbacks.onMessage(`No annotated frame: the server cannot be reached (${err.message})`);
      return;
    }
    if (!response.ok) {
      const body = await response.json().catch(() => ({}));
      this.callbacks.onMessage(`No annotated frame: ${body.detail || response.statusText}`);
      return;
    }
    const url = URL.createObjectURL(await response.blob());
    const a = document.createElement("a");
    a.href = url;
    a.download = `sequence-${id}-snapshot-${info.snapshot}-rank-${rank}.png`;
    a.hidden = true;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  }

  // The sensor size of the sequence (every frame of a pass has the same).
  sensor() {
    const any = this.frames && this.frames.values().next().value;
    if (any) return { width: any.width, height: any.height };
    const cam = this.detail?.telemetry?.camera;
    return cam ? { width: cam.width, height: cam.height } : { width: 4, height: 3 };
  }

  resize() {
    if (this.card.hidden) return;
    const { width, height } = this.sensor();
    const cssWidth = Math.max(200, Math.floor(this.canvas.parentElement.clientWidth));
    const cssHeight = Math.min(MAX_HEIGHT_PX, Math.round(cssWidth * height / width));
    if (this.canvas.width === cssWidth && this.canvas.height === cssHeight) {
      // The same size: a new sequence's frames are still shown whole, not at the last one's zoom and place.
      if (this.fitted) this.fit();
      return;
    }
    // Keep the sensor point at the centre where it was.
    const cx = (this.canvas.width / 2 - this.ox) / this.zoom, cy = (this.canvas.height / 2 - this.oy) / this.zoom;
    this.canvas.width = cssWidth;
    this.canvas.height = cssHeight;
    this.canvas.style.height = `${cssHeight}px`;
    if (this.fitted) this.fit();
    else { this.ox = cssWidth / 2 - cx * this.zoom; this.oy = cssHeight / 2 - cy * this.zoom; }
    this.draw();
  }

  fitZoom() {
    const { width, height } = this.sensor();
    return Math.min(this.canvas.width / width, this.canvas.height / height);
  }

  fit() {
    const { width, height } = this.sensor();
    this.zoom = this.fitZoom();
    this.ox = (this.canvas.width - width * this.zoom) / 2;
    this.oy = (this.canvas.height - height * this.zoom) / 2;
    this.fitted = true;
  }

  // Zoom by a factor about a canvas point (the centre by default).
  zoomBy(factor, px = this.canvas.width / 2, py = this.canvas.height / 2) {
    const zoom = Math.min(MAX_ZOOM, Math.max(this.fitZoom(), this.zoom * factor));
    if (zoom === this.zoom) return;
    const sx = (px - this.ox) / this.zoom, sy = (py - this.oy) / this.zoom;
    this.zoom = zoom;
    this.ox = px - sx * zoom;
    this.oy = py - sy * zoom;
    this.fitted = Math.abs(zoom - this.fitZoom()) < 1e-9;
    if (this.fitted) this.fit();
    this.draw();
  }

  // Canvas position of a sensor point (pixel centres at +0.5).
  toCanvas(x, y) { return [this.ox + (x + 0.5) * this.zoom, this.oy + (y + 0.5) * this.zoom]; }

  eventPoint(e) {
    const rect = this.canvas.getBoundingClientRect();
    return [(e.clientX - rect.left) * this.canvas.width / rect.width, (e.clientY - rect.top) * this.canvas.height / rect.height];
  }

  wheel(e) {
    if (!this.current()) return;
    e.preventDefault();
    const [px, py] = this.eventPoint(e);
    this.zoomBy(Math.exp(-e.deltaY * WHEEL_RATE), px, py);
  }

  press(e) {
    if (e.button !== 0) return;
    const [px, py] = this.eventPoint(e);
    this.drag = { px, py, ox: this.ox, oy: this.oy, moved: false };
    e.preventDefault();
  }

  move(e) {
    if (this.drag) {
      const [px, py] = this.eventPoint(e);
      const dx = px - this.drag.px, dy = py - this.drag.py;
      if (!this.drag.moved && Math.hypot(dx, dy) < DRAG_THRESHOLD_PX) return;
      this.drag.moved = true;
      this.ox = this.drag.ox + dx;
      this.oy = this.drag.oy + dy;
      this.fitted = false;
      this.canvas.classList.add("dragging");
      this.tip.hidden = true;
      this.draw();
      return;
    }
    if (e.target !== this.canvas) return;
    const hit = this.hitAt(...this.eventPoint(e));
    this.canvas.style.cursor = hit && hit.kind === "detection" && hit.track !== null ? "pointer" : "";
    if (!hit) { this.tip.hidden = true; return; }
    this.tip.textContent = hit.text;
    this.tip.hidden = false;
    const rect = this.canvas.getBoundingClientRect();
    this.tip.style.left = `${Math.min(e.clientX - rect.left + 14, rect.width - 240)}px`;
    this.tip.style.top = `${e.clientY - rect.top + 14}px`;
  }

  release(e) {
    const drag = this.drag;
    if (!drag) return;
    this.drag = null;
    this.canvas.classList.remove("dragging");
    if (drag.moved || e.target !== this.canvas) return;
    const hit = this.hitAt(...this.eventPoint(e));
    if (!hit) return;
    if (hit.kind === "detection" && hit.track !== null) { this.callbacks.onToggleTrack(hit.track); return; }
    if (hit.kind === "detection") {
      this.callbacks.onMessage(`That source is ${hit.reason ? `a ${hit.reason.replaceAll("_", " ")}` : "untracked"}, ` +
        'not a track: switch on "Pick points by hand" and click it in the snapshots to add it to the pattern.');
    } else {
      this.callbacks.onMessage(`${hit.text}: the detector did not report it as a source.`);
    }
  }

  hitAt(x, y) {
    let best = null;
    const order = { detection: 0, rejected: 1, hot: 2 };
    for (const h of this.hits) {
      const d = Math.hypot(h.x - x, h.y - y);
      if (d > h.r + 3) continue;
      if (!best || order[h.kind] < order[best.h.kind] || (order[h.kind] === order[best.h.kind] && d < best.d)) best = { h, d };
    }
    return best ? best.h : null;
  }

  draw() {
    const { ctx, canvas } = this;
    ctx.fillStyle = "#05070b";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    this.hits = [];
    const info = this.current();
    const snapshots = this.detail?.telemetry?.snapshots || [];
    // Named as the player names it: by its index in the file, its position in words.
    const name = snapshotName(this.index, { snapshots, reference: this.detail?.extraction.reference_snapshot, count: true });
    $("frame-caption").textContent = this.frames && this.frames.size
      ? name + (info ? ` · ${info.width}×${info.height} px` +
        (info.scale > 1 ? `, shown 1:${info.scale}` : "") : " · no image kept of this snapshot")
      : "";
    $("frame-zoom-label").textContent = `${Math.round(this.zoom * 100)} %`;
    canvas.dataset.zoom = this.zoom.toFixed(4);
    canvas.dataset.snapshot = String(this.index);
    canvas.dataset.image = "";
    canvas.dataset.markers = "[]";
    $("frame-annotated").disabled = !info;
    if (!info) return;
    const img = this.images.get(info.url);
    if (img && img.complete && img.naturalWidth) {
      // Smooth when the image is shrunk; its pixels as squares when zoomed in.
      ctx.imageSmoothingEnabled = this.zoom * info.scale < 2;
      ctx.drawImage(img, this.ox, this.oy, img.naturalWidth * info.scale * this.zoom, img.naturalHeight * info.scale * this.zoom);
      canvas.dataset.image = info.url;
    } else {
      ctx.fillStyle = "#8b97a8";
      ctx.font = "13px system-ui, sans-serif";
      ctx.fillText(img && img.failed ? "the image cannot be loaded" : "loading the image...", 12, 22);
    }
    const overlay = info.overlay;
    const markers = [];
    const ex = this.detail.extraction;
    if ($("frame-show-hot").checked) {
      const size = Math.max(5, this.zoom);
      ctx.strokeStyle = COLOURS.hot; ctx.lineWidth = 1.5;
      for (const [x, y] of overlay.hot_pixels) {
        const [cx, cy] = this.toCanvas(x, y);
        if (!this.visible(cx, cy)) continue;
        ctx.strokeRect(cx - size / 2, cy - size / 2, size, size);
        this.hits.push({ kind: "hot", x: cx, y: cy, r: size / 2, text: `hot pixel (${x}, ${y}) of the camera's map` });
        markers.push({ kind: "hot", x: cx, y: cy });
      }
    }
    if ($("frame-show-rejected").checked) {
      for (const b of overlay.rejected) {
        const [cx, cy] = this.toCanvas(b.x, b.y);
        if (!this.visible(cx, cy)) continue;
        // A star fainter than those reported: small and grey; a blob that is no star: orange.
        const fainter = b.reason.startsWith("not_brightest");
        const r = fainter ? Math.max(4, 2 * this.zoom) : Math.max(6, 2.5 * this.zoom);
        ctx.strokeStyle = fainter ? COLOURS.fainter : COLOURS.rejected;
        ctx.lineWidth = fainter ? 1 : 1.5;
        ctx.beginPath();
        ctx.moveTo(cx, cy - r); ctx.lineTo(cx + r, cy); ctx.lineTo(cx, cy + r); ctx.lineTo(cx - r, cy); ctx.closePath();
        ctx.stroke();
        this.hits.push({ kind: "rejected", x: cx, y: cy, r, text: `rejected blob at (${b.x.toFixed(1)}, ${b.y.toFixed(1)}): ${reasonText(b.reason)}` });
        markers.push({ kind: "rejected", x: cx, y: cy, reason: b.reason });
      }
    }
    if ($("frame-show-detections").checked) {
      const r = Math.max(7, 3.5 * this.zoom);
      ctx.font = "12px system-ui, sans-serif";
      for (const d of overlay.detections) {
        const [cx, cy] = this.toCanvas(d.x, d.y);
        const track = ex.sources[this.index]?.[d.source] ?? null;
        const reason = ex.rejected[this.index]?.[d.source] ?? null;
        if (!this.visible(cx, cy)) continue;
        const inside = track !== null && this.inPattern.has(track);
        ctx.strokeStyle = track === null ? COLOURS.untracked : inside ? trackColour(track) : COLOURS.out;
        ctx.lineWidth = 2;
        ctx.setLineDash(track !== null && !inside ? [3, 3] : []);
        ctx.beginPath(); ctx.arc(cx, cy, r, 0, 2 * Math.PI); ctx.stroke();
        ctx.setLineDash([]);
        const label = track !== null ? `T${track}` : (reason || "").replaceAll("_", " ");
        // On its dark box at the circle's upper right; inside the canvas for a source at its edge.
        const box = label ? placeLabel({ cx, cy, r, w: ctx.measureText(label).width + 4, h: 14, width: canvas.width,
          gap: 2, above: r - 2 }) : null;
        if (box) {
          ctx.fillStyle = "#000a";
          ctx.fillRect(box.x, box.y, box.w, box.h);
          ctx.fillStyle = track === null ? COLOURS.untracked : inside ? trackColour(track) : COLOURS.out;
          ctx.fillText(label, box.x + 2, box.y + 11);
        }
        const what = track !== null ? `T${track}${inside ? "" : " (out of the pattern)"}` : (reason ? reason.replaceAll("_", " ") : "untracked");
        this.hits.push({ kind: "detection", x: cx, y: cy, r, track, reason,
          text: `${what} · source ${d.source} at (${d.x.toFixed(2)}, ${d.y.toFixed(2)}), brightness ${Math.round(d.brightness ?? 0)}` +
            (d.flags.length ? ` · ${reasonText(d.flags.join("+"))}` : "") + (track !== null ? " · click: in / out of the pattern" : "") });
        markers.push({ kind: "detection", x: cx, y: cy, track, source: d.source,
          label: box && { text: label, x: round1(box.x), y: round1(box.y), w: round1(box.w), h: box.h } });
      }
    }
    // What was drawn where, for whoever inspects the page (the browser tests).
    canvas.dataset.markers = JSON.stringify(markers.map((m) => ({ ...m, x: round1(m.x), y: round1(m.y) })));
  }

  visible(cx, cy) {
    return cx > -20 && cy > -20 && cx < this.canvas.width + 20 && cy < this.canvas.height + 20;
  }
}

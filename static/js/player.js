// Snapshot player: the sequence on the sensor frame, sources coloured by track,
// rejected sources marked by reason, tracks drawn as trails; play / step / slider;
// clicks toggle tracks in or out of the pattern, or pick points by hand.
import { $, placeLabel, sequenceTime, snapshotName, trackColour } from "./dom.js";

const CLICK_RADIUS_CSS = 10;   // how close (CSS pixels) a click must be to a source or trail
const SNAP_RADIUS_PX = 6;      // a picked point snaps to a reported source this close (sensor pixels)
const PLAY_INTERVAL_MS = 450;
const LABEL_FONT_PX = 11;      // track names (T3) beside their sources

export class SnapshotPlayer {
  constructor({ onToggleTrack, onPick, onRemoveManual, onMessage, onShow }) {
    this.canvas = $("player-canvas");
    this.ctx = this.canvas.getContext("2d");
    this.slider = $("snapshot-slider");
    this.callbacks = { onToggleTrack, onPick, onRemoveManual, onMessage, onShow };
    this.detail = null;
    this.index = 0;
    this.timer = null;
    this.picking = false;
    this.highlight = null;   // a track picked in the sky view, ringed here
    this.slider.addEventListener("input", () => this.show(Number(this.slider.value)));
    $("step-back").addEventListener("click", () => this.step(-1));
    $("step-fwd").addEventListener("click", () => this.step(+1));
    $("play").addEventListener("click", () => this.togglePlay());
    this.canvas.addEventListener("click", (e) => this.click(e));
  }

  setSequence(detail) {
    const first = !this.detail || this.detail.id !== detail.id;
    this.detail = detail;
    const cam = detail.telemetry.camera;
    // The sensor fitted into a canvas of one size whatever the camera: the panels below keep their place
    // from sequence to sequence (a taller sensor made the canvas taller, and a click meant for Next, where it
    // had been, landed on the player and took a track out of the pattern).
    this.scale = Math.min(this.canvas.width / cam.width, this.canvas.height / cam.height);
    this.ox = (this.canvas.width - cam.width * this.scale) / 2;
    this.oy = (this.canvas.height - cam.height * this.scale) / 2;
    this.sensor = [cam.width * this.scale, cam.height * this.scale];
    this.canvas.dataset.mapping = JSON.stringify({ scale: this.scale, ox: this.ox, oy: this.oy });
    const n = detail.telemetry.snapshots.length;
    this.slider.max = Math.max(0, n - 1);
    if (first) { this.stop(); this.index = detail.extraction.reference_snapshot ?? 0; this.highlight = null; }
    this.index = Math.min(this.index, n - 1);
    this.inPattern = new Set(detail.pattern.points.filter((p) => p.track !== null).map((p) => p.track));
    this.draw();
  }

  setPicking(on) {
    this.picking = on;
    this.canvas.classList.toggle("picking", on);
  }

  step(delta) {
    if (!this.detail) return;
    const n = this.detail.telemetry.snapshots.length;
    this.show((this.index + delta + n) % n);
  }

  show(index) { this.index = index; this.draw(); }

  // Ring a track (picked in the sky view) and show it: in the snapshot shown if it was seen
  // there, else in the reference snapshot or its first sighting.
  showTrack(track) {
    if (!this.detail) return;
    const t = this.detail.extraction.tracks.find((x) => x.id === track);
    if (!t) return;
    this.highlight = track;
    const ref = this.detail.extraction.reference_snapshot;
    if (!t.snapshots.includes(this.index)) this.index = t.snapshots.includes(ref) ? ref : t.snapshots[0];
    this.draw();
  }

  togglePlay() { if (this.timer) this.stop(); else this.play(); }

  play() {
    if (!this.detail) return;
    this.timer = setInterval(() => this.step(+1), PLAY_INTERVAL_MS);
    $("play").innerHTML = "&#10073;&#10073; Pause";
  }

  stop() {
    clearInterval(this.timer);
    this.timer = null;
    $("play").innerHTML = "&#9654; Play";
  }

  toCanvas(x, y) { return [this.ox + (x + 0.5) * this.scale, this.oy + (y + 0.5) * this.scale]; }

  // Sources of snapshot i with their extraction verdicts.
  sourcesOf(i) {
    const ex = this.detail.extraction;
    return this.detail.telemetry.snapshots[i].sources.map((s, j) => ({
      ...s, index: j, track: ex.sources[i]?.[j] ?? null, reason: ex.rejected[i]?.[j] ?? null,
    }));
  }

  draw() {
    const { ctx, canvas } = this;
    ctx.fillStyle = "#05070b";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    this.labels = [];
    canvas.dataset.labels = "[]";
    if (!this.detail) return;
    if (this.ox > 0.5 || this.oy > 0.5) {   // the sensor's edges, where it does not fill the canvas
      ctx.strokeStyle = "rgba(150,150,160,0.35)"; ctx.lineWidth = 1;
      ctx.strokeRect(this.ox, this.oy, ...this.sensor);
    }
    const snapshots = this.detail.telemetry.snapshots;
    const ex = this.detail.extraction;
    this.slider.value = this.index;
    const ref = ex.reference_snapshot;
    // Named by its index in the file (0-based, as the API and the CLI name it), with its position.
    const name = snapshotName(this.index, { snapshots, reference: ref, count: true });
    $("snapshot-label").textContent = name;
    this.slider.setAttribute("aria-valuetext", name);
    const time = snapshots[this.index]?.time;
    $("player-caption").textContent = time ? sequenceTime(time, this.detail.telemetry) : "";

    // Trails: every track through all its sightings, faint; dashed grey when out of the pattern.
    ctx.lineWidth = 1.5;
    for (const t of ex.tracks) {
      const inside = this.inPattern.has(t.id);
      ctx.strokeStyle = inside ? trackColour(t.id, 0.45) : "rgba(150,150,160,0.35)";
      ctx.setLineDash(inside ? [] : [4, 4]);
      ctx.beginPath();
      t.xy.forEach(([x, y], k) => { const [cx, cy] = this.toCanvas(x, y); if (k) ctx.lineTo(cx, cy); else ctx.moveTo(cx, cy); });
      ctx.stroke();
    }
    ctx.setLineDash([]);

    for (const s of this.sourcesOf(this.index)) this.drawSource(s);
    const ringed = this.highlight === null ? null : this.sourcesOf(this.index).find((s) => s.track === this.highlight);
    if (ringed) {
      const [cx, cy] = this.toCanvas(ringed.x, ringed.y);
      ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(cx, cy, 13, 0, 2 * Math.PI); ctx.stroke();
    }

    // Points picked by hand in this snapshot.
    for (const p of this.detail.pattern.definition.manual_points || []) {
      if (p.snapshot !== this.index) continue;
      const [cx, cy] = this.toCanvas(p.x, p.y);
      ctx.fillStyle = "#ffe066";
      ctx.beginPath();
      ctx.moveTo(cx, cy - 7); ctx.lineTo(cx + 7, cy); ctx.lineTo(cx, cy + 7); ctx.lineTo(cx - 7, cy); ctx.closePath();
      ctx.fill();
    }
    // What was drawn where, for whoever inspects the page (the browser tests check labels stay on the canvas).
    canvas.dataset.labels = JSON.stringify(this.labels.map(({ text, x, y, w, h }) => ({
      text, x: Math.round(x * 10) / 10, y: Math.round(y * 10) / 10, w: Math.round(w * 10) / 10, h })));
    // Whoever follows the snapshot shown (the frame panel).
    if (this.callbacks.onShow) this.callbacks.onShow(this.index);
  }

  drawSource(s) {
    const { ctx } = this;
    const [cx, cy] = this.toCanvas(s.x, s.y);
    const r = 2.5 + 4 * Math.min(1, Math.max(0, (s.brightness ?? 0) / 255));
    if (s.track !== null) {
      const inside = this.inPattern.has(s.track);
      ctx.beginPath();
      ctx.arc(cx, cy, r, 0, 2 * Math.PI);
      if (inside) { ctx.fillStyle = trackColour(s.track); ctx.fill(); }
      else { ctx.setLineDash([2, 2]); ctx.strokeStyle = "#aaa"; ctx.lineWidth = 1.5; ctx.stroke(); ctx.setLineDash([]); }
      ctx.fillStyle = inside ? "#dfe6ee" : "#777";
      this.drawLabel(`T${s.track}`, cx, cy, r);
    } else if (s.reason === "ghost") {
      ctx.strokeStyle = "#f85149"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.moveTo(cx - 5, cy - 5); ctx.lineTo(cx + 5, cy + 5); ctx.moveTo(cx + 5, cy - 5); ctx.lineTo(cx - 5, cy + 5); ctx.stroke();
    } else if (s.reason === "hot_pixel") {
      ctx.fillStyle = "#f06595"; ctx.fillRect(cx - 4, cy - 4, 8, 8);
    } else if (s.reason === "outlier") {
      ctx.fillStyle = "#adb5bd";
      ctx.beginPath(); ctx.moveTo(cx, cy - 6); ctx.lineTo(cx + 5, cy + 4); ctx.lineTo(cx - 5, cy + 4); ctx.closePath(); ctx.fill();
    } else {
      ctx.strokeStyle = "#777"; ctx.beginPath(); ctx.arc(cx, cy, 3, 0, 2 * Math.PI); ctx.stroke();
    }
  }

  // A source's name beside it, moved inside the canvas for a source at the sensor's edge (placeLabel), and
  // to another corner of the source when a label drawn already is there (a double star's two names were
  // drawn over each other); the baseline 9 px below the box's top leaves the descenders their 2 px.
  drawLabel(text, cx, cy, r) {
    const { ctx } = this;
    ctx.font = `${LABEL_FONT_PX}px system-ui, sans-serif`;
    const w = ctx.measureText(text).width, h = LABEL_FONT_PX, gap = 3;
    const first = placeLabel({ cx, cy, r, w, h, width: this.canvas.width, gap, above: 1 });
    const corners = [first, { x: first.x, y: cy + r + gap }, { x: cx - r - gap - w, y: first.y },
      { x: cx - r - gap - w, y: cy + r + gap }, { x: cx + r + gap, y: cy - 2 * h - gap }, { x: cx + r + gap, y: cy + h + gap + r }]
      .map((b) => ({ x: b.x, y: b.y, w, h }))
      .filter((b) => b.x >= 0 && b.y >= 0 && b.x + w <= this.canvas.width && b.y + h <= this.canvas.height);
    const overlaps = (a, b) => a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
    const box = corners.find((b) => !this.labels.some((l) => overlaps(l, b))) ?? first;
    ctx.fillText(text, box.x, box.y + LABEL_FONT_PX - 2);
    this.labels.push({ text, ...box });
  }

  // Sensor pixel under a mouse event.
  eventToSensor(e) {
    const rect = this.canvas.getBoundingClientRect();
    const cssScale = this.canvas.width / rect.width;
    const cx = (e.clientX - rect.left) * cssScale, cy = (e.clientY - rect.top) * cssScale;
    return { x: (cx - this.ox) / this.scale - 0.5, y: (cy - this.oy) / this.scale - 0.5,
      cssPerSensor: this.scale / cssScale };
  }

  click(e) {
    if (!this.detail) return;
    const { x, y, cssPerSensor } = this.eventToSensor(e);
    const radius = CLICK_RADIUS_CSS / cssPerSensor;
    const sources = this.sourcesOf(this.index);
    const nearest = (items) => items.reduce((best, s) => {
      const d = Math.hypot(s.x - x, s.y - y);
      return d < best.d ? { s, d } : best;
    }, { s: null, d: Infinity });

    if (this.picking) {
      const snap = nearest(sources);
      const point = snap.d <= SNAP_RADIUS_PX ? { x: snap.s.x, y: snap.s.y } : { x, y };
      this.callbacks.onPick(this.index, Math.round(point.x * 100) / 100, Math.round(point.y * 100) / 100);
      return;
    }
    const manual = (this.detail.pattern.definition.manual_points || [])
      .map((p, k) => ({ ...p, k })).filter((p) => p.snapshot === this.index);
    const m = nearest(manual);
    if (m.d <= radius) { this.callbacks.onRemoveManual(m.s.k); return; }
    const hit = nearest(sources);
    if (hit.d <= radius && hit.s.track !== null) { this.callbacks.onToggleTrack(hit.s.track); return; }
    // A trail: the nearest sighting of any track.
    const trail = nearest(this.detail.extraction.tracks.flatMap((t) => t.xy.map(([tx, ty]) => ({ x: tx, y: ty, track: t.id }))));
    if (trail.d <= radius) { this.callbacks.onToggleTrack(trail.s.track); return; }
    if (hit.d <= radius) {
      const what = hit.s.reason ? hit.s.reason.replace("_", " ") : "untracked source";
      this.callbacks.onMessage(`That is a ${what}, not a track: switch on "Pick points by hand" to add it to the pattern.`);
    }
  }
}

// rectify view: the page of `rectify view` / `stereo view` (docs/view.md). Plain JavaScript and canvas, no
// library. Data come from the server's (or a static export's) files: api/manifest.json, api/layout.json,
// api/obs/<i>.json, api/tracks/<b>.json, api/table/<t>.json, tiles/<r>/<level>/<x>_<y>.png, files/<path>.
//
// URL parameters: view=layout | image:<i> | raster:<r> | table:<t>; select=<id> (select a point, as a click
// would); click=<id> (a real click event at the point's place on the canvas, through the hit test);
// zoom=full with at=<x>,<y> (full resolution at that pixel); exag=<factor>; worst=<N>; flag=<all|flagged|ok|
// control|check|tie>.
// The DOM records what rendered (body data-state, data-view, data-level, data-tiles-loaded, data-points;
// #detail data-selected; rows tr[data-key]) so a headless browser can read it back.
"use strict";

const S = {
  manifest: null, view: null, tiles: new Map(), tileOrder: [], pending: 0, loaded: 0,
  cam: { cx: 0, cy: 0, scale: 1, yUp: false }, points: [], selected: null, layout: null,
  tables: new Map(), obs: new Map(), buckets: new Map(), exag: 100, worst: 0, flag: "all", imageFilter: "",
  params: new URLSearchParams(location.search), drawn: 0, errors: 0,
};
const $ = (id) => document.getElementById(id);
const CLASSES = [[1, "#2e9e44", "< 1"], [2, "#c8b400", "1 - 2"], [3, "#f08c00", "2 - 3"], [Infinity, "#d7191c", ">= 3"]];
const MAX_TILES = 400;

window.addEventListener("error", (e) => { S.errors += 1; document.body.dataset.error = String(e.message); });

function colourOf(z) {
  if (z === null || z === undefined || !isFinite(z)) return "#888";
  for (const [lim, c] of CLASSES) if (Math.abs(z) < lim) return c;
  return CLASSES[CLASSES.length - 1][1];
}

function fmt(v, d = 4) {
  if (v === null || v === undefined) return "-";
  if (typeof v !== "number") return String(v);
  if (Number.isInteger(v) && Math.abs(v) < 1e7) return String(v);
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e7)) return v.toExponential(3);
  return v.toFixed(a >= 1000 ? 3 : d);
}

async function getJSON(path) {
  const r = await fetch(path);
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

function setStatus(text) { $("status").textContent = text; }

// ------------------------------------------------------------------ camera (world <-> screen)
const canvas = () => $("map");
function toScreen(x, y) {
  const c = canvas(), cam = S.cam;
  return [c.width / 2 + (x - cam.cx) * cam.scale, c.height / 2 + (cam.yUp ? -1 : 1) * (y - cam.cy) * cam.scale];
}
function toWorld(sx, sy) {
  const c = canvas(), cam = S.cam;
  return [cam.cx + (sx - c.width / 2) / cam.scale, cam.cy + (cam.yUp ? -1 : 1) * (sy - c.height / 2) / cam.scale];
}
function extent(xs, ys) {  // [x0, y0, x1, y1] by a loop (spreading 10^5 values into Math.min overflows the stack)
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (let k = 0; k < xs.length; k++) {
    x0 = Math.min(x0, xs[k]); x1 = Math.max(x1, xs[k]); y0 = Math.min(y0, ys[k]); y1 = Math.max(y1, ys[k]);
  }
  return [x0, y0, x1, y1];
}

function fit(x0, y0, x1, y1) {
  const c = canvas();
  S.cam.cx = (x0 + x1) / 2; S.cam.cy = (y0 + y1) / 2;
  S.cam.scale = 0.92 * Math.min(c.width / Math.max(x1 - x0, 1e-9), c.height / Math.max(y1 - y0, 1e-9));
}

// ------------------------------------------------------------------ tiles
function rasterOf() {
  const v = S.view;
  if (!v) return null;
  if (v.kind === "raster") return S.manifest.rasters[v.n];
  if (v.kind === "image") {
    const im = S.manifest.images[v.n];
    return im && im.raster !== null ? S.manifest.rasters[im.raster] : null;
  }
  return null;
}

function tileLevel(r) {
  const perScreen = 1 / S.cam.scale;  // raster pixels per screen pixel
  let s = 1;
  while (s * 2 <= perScreen && s * 2 <= 2 ** r.max_level) s *= 2;
  return r.max_level - Math.round(Math.log2(s));
}

function staticLimit(r) {
  const st = S.manifest.static;
  return st && st.levels && st.levels[r.id] !== undefined ? st.levels[r.id] : r.max_level;
}

function requestTile(r, z, x, y) {
  const key = `${r.id}/${z}/${x}_${y}`;
  let t = S.tiles.get(key);
  if (t) return t;
  const img = new Image();
  t = { img, ok: false, failed: false };
  S.tiles.set(key, t);
  S.tileOrder.push(key);
  S.pending += 1;
  img.onload = () => {
    t.ok = true; S.pending -= 1; S.loaded += 1;
    document.body.dataset.tilesLoaded = String(S.loaded);
    draw();  // at once, not on the next frame: what is on the screen follows what has arrived
    if (!document.body.dataset.firstTileMs) document.body.dataset.firstTileMs = String(Math.round(performance.now()));
  };
  img.onerror = () => { t.failed = true; S.pending -= 1; scheduleDraw(); };
  img.src = `tiles/${key}.png`;
  while (S.tileOrder.length > MAX_TILES) S.tiles.delete(S.tileOrder.shift());
  return t;
}

function drawTilesOf(ctx, r, z, request) {
  const s = 2 ** (r.max_level - z), span = r.tile * s;
  const c = canvas();
  const [wx0, wy0] = toWorld(0, 0), [wx1, wy1] = toWorld(c.width, c.height);
  const tx0 = Math.max(0, Math.floor(Math.min(wx0, wx1) / span)), tx1 = Math.min(Math.ceil(r.width / span) - 1, Math.floor(Math.max(wx0, wx1) / span));
  const ty0 = Math.max(0, Math.floor(Math.min(wy0, wy1) / span)), ty1 = Math.min(Math.ceil(r.height / span) - 1, Math.floor(Math.max(wy0, wy1) / span));
  let all = true;
  for (let ty = ty0; ty <= ty1; ty++) {
    for (let tx = tx0; tx <= tx1; tx++) {
      const key = `${r.id}/${z}/${tx}_${ty}`;
      const t = request ? requestTile(r, z, tx, ty) : S.tiles.get(key);
      if (!t || !t.ok) { all = false; continue; }
      const w = Math.min(span, r.width - tx * span), h = Math.min(span, r.height - ty * span);
      const [sx, sy] = toScreen(tx * span - 0.5, ty * span - 0.5);
      ctx.drawImage(t.img, sx, sy, w * S.cam.scale, h * S.cam.scale);
    }
  }
  return all;
}

function drawRaster(ctx, r) {
  ctx.imageSmoothingEnabled = S.cam.scale < 1;
  const z = Math.min(tileLevel(r), staticLimit(r));
  drawTilesOf(ctx, r, 0, true);  // the whole raster, coarse, always
  for (let lz = Math.max(1, z - 2); lz < z; lz++) drawTilesOf(ctx, r, lz, false);
  const complete = z === 0 ? true : drawTilesOf(ctx, r, z, true);
  document.body.dataset.level = String(z);
  document.body.dataset.maxLevel = String(r.max_level);
  document.body.dataset.fullResolution = z === r.max_level && S.cam.scale >= 1 && complete ? "yes" : "no";
  document.body.dataset.tilesLoaded = String(S.loaded);
}

// ------------------------------------------------------------------ points of a view
// a point: {id, x, y, vx, vy, z, flag, kind, row (for the detail table), i (image)}
function filtered() {
  let pts = S.points;
  const f = S.flag;
  if (f === "flagged") pts = pts.filter((p) => p.flag);
  else if (f === "ok") pts = pts.filter((p) => !p.flag);
  else if (f !== "all") pts = pts.filter((p) => p.kind === f);
  if (S.worst > 0) {
    pts = [...pts].sort((a, b) => (Math.abs(b.z ?? -1)) - (Math.abs(a.z ?? -1))).slice(0, S.worst);
  }
  return pts;
}

function drawMarker(ctx, p, sx, sy) {
  ctx.fillStyle = colourOf(p.z);
  ctx.strokeStyle = "#000";
  ctx.lineWidth = 1;
  if (p.kind === "control") {
    ctx.beginPath(); ctx.moveTo(sx, sy - 6); ctx.lineTo(sx + 5.5, sy + 4); ctx.lineTo(sx - 5.5, sy + 4); ctx.closePath();
    ctx.fill(); ctx.stroke();
  } else if (p.kind === "check") {
    ctx.fillRect(sx - 4.5, sy - 4.5, 9, 9); ctx.strokeRect(sx - 4.5, sy - 4.5, 9, 9);
  } else {
    ctx.beginPath(); ctx.arc(sx, sy, 3, 0, 2 * Math.PI); ctx.fill();
  }
  if (p.flag) {
    ctx.strokeStyle = "#d00"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(sx - 6, sy - 6); ctx.lineTo(sx + 6, sy + 6); ctx.moveTo(sx + 6, sy - 6); ctx.lineTo(sx - 6, sy + 6); ctx.stroke();
  }
}

const placeable = (p) => typeof p.x === "number" && typeof p.y === "number" && isFinite(p.x) && isFinite(p.y);

function drawPoints(ctx) {
  const pts = filtered();
  let n = 0;
  const c = canvas();
  for (const p of pts) {
    if (!placeable(p)) continue;  // no position (a control point missing from a pair's matches): listed only
    const [sx, sy] = toScreen(p.x, p.y);
    if (sx < -50 || sy < -50 || sx > c.width + 50 || sy > c.height + 50) continue;
    if (p.vx !== null && p.vy !== null && isFinite(p.vx) && isFinite(p.vy)) {
      const [ex, ey] = toScreen(p.x + S.exag * p.vx, p.y + S.exag * p.vy);
      ctx.strokeStyle = colourOf(p.z); ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.moveTo(sx, sy); ctx.lineTo(ex, ey); ctx.stroke();
    }
    drawMarker(ctx, p, sx, sy);
    n += 1;
  }
  if (S.selected) {
    for (const p of S.points) {
      if (p.id !== S.selected) continue;
      const [sx, sy] = toScreen(p.x, p.y);
      ctx.strokeStyle = "#00e5ff"; ctx.lineWidth = 2.5;
      ctx.beginPath(); ctx.arc(sx, sy, 10, 0, 2 * Math.PI); ctx.stroke();
    }
  }
  document.body.dataset.points = String(n);
  return pts;
}

// ------------------------------------------------------------------ layout (block in plan)
function drawLayout(ctx) {
  const L = S.layout;
  ctx.lineWidth = 1;
  for (const im of L.images) {
    if (!im.footprint) continue;
    ctx.strokeStyle = "rgba(40,70,120,0.55)";
    ctx.beginPath();
    im.footprint.forEach(([x, y], k) => { const [sx, sy] = toScreen(x, y); if (k) ctx.lineTo(sx, sy); else ctx.moveTo(sx, sy); });
    ctx.closePath(); ctx.stroke();
  }
  if (L.points) {
    ctx.fillStyle = "rgba(90,90,90,0.6)";
    for (let k = 0; k < L.points.x.length; k++) {
      const [sx, sy] = toScreen(L.points.x[k], L.points.y[k]);
      ctx.fillRect(sx - 1, sy - 1, 2, 2);
    }
  }
  const sel = S.selected && S.track ? S.track : null;
  if (sel && sel.point) {
    const [px, py] = toScreen(sel.point.x, sel.point.y);
    ctx.strokeStyle = "#00a5bf"; ctx.lineWidth = 1;
    for (const o of sel.obs) {
      const im = L.images[o[0]];
      if (!im) continue;
      const [sx, sy] = toScreen(im.position[0], im.position[1]);
      ctx.beginPath(); ctx.moveTo(sx, sy); ctx.lineTo(px, py); ctx.stroke();
    }
  }
  const ell = S.exag;
  for (const im of L.images) {
    const [sx, sy] = toScreen(im.position[0], im.position[1]);
    if (im.std && im.std.x && im.std.y) {
      ctx.strokeStyle = "#7b2cbf"; ctx.lineWidth = 1;
      ctx.beginPath(); ctx.ellipse(sx, sy, Math.max(0.5, im.std.x * ell * S.cam.scale), Math.max(0.5, im.std.y * ell * S.cam.scale), 0, 0, 2 * Math.PI); ctx.stroke();
    }
    ctx.fillStyle = "#24313f"; ctx.beginPath(); ctx.arc(sx, sy, 3.5, 0, 2 * Math.PI); ctx.fill();
  }
  drawPoints(ctx);
}

// ------------------------------------------------------------------ drawing
let drawQueued = false;
function scheduleDraw() {
  if (drawQueued) return;
  drawQueued = true;
  requestAnimationFrame(() => { drawQueued = false; draw(); });
}

function draw() {
  const c = canvas();
  const ctx = c.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.fillStyle = "#dfe3e8"; ctx.fillRect(0, 0, c.width, c.height);
  if (!S.view) return;
  const r = rasterOf();
  if (S.view.kind === "layout") drawLayout(ctx);
  else {
    if (r) drawRaster(ctx, r);
    else if (S.view.kind === "image") {
      const im = S.manifest.images[S.view.n];
      if (im.width) {
        const [x0, y0] = toScreen(-0.5, -0.5);
        ctx.fillStyle = "#f8f8f8"; ctx.fillRect(x0, y0, im.width * S.cam.scale, im.height * S.cam.scale);
      }
    }
    drawPoints(ctx);
  }
  drawScaleBar(ctx);
  S.drawn += 1;
  document.body.dataset.draws = String(S.drawn);
}

function drawScaleBar(ctx) {
  const c = canvas();
  const units = S.view.kind === "layout" ? (S.manifest.units || "m") : (S.view.units || "px");
  let len = 1;
  while (len * S.cam.scale < 60) len *= 10;
  while (len * S.cam.scale > 300) len /= 10;
  const w = len * S.cam.scale;
  ctx.fillStyle = "rgba(255,255,255,0.8)"; ctx.fillRect(10, c.height - 30, w + 70, 22);
  ctx.strokeStyle = "#000"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(15, c.height - 14); ctx.lineTo(15 + w, c.height - 14); ctx.stroke();
  ctx.fillStyle = "#000"; ctx.font = "11px sans-serif";
  ctx.fillText(`${fmt(len, 3)} ${units}`, 20 + w, c.height - 12);
}

const RAMP = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];  // as rectify.raster.viewtiles

function drawRasterLegend(ctx, info) {
  const [lo, hi] = info.limits;
  ctx.fillStyle = "#000";
  ctx.fillText(info.label, 4, 12);
  if (info.mode === "ramp") {
    for (let k = 0; k < 240; k++) {
      const t = (k / 239) * (RAMP.length - 1), i = Math.min(Math.floor(t), RAMP.length - 2), f = t - i;
      const c = RAMP[i].map((a, j) => Math.round(a * (1 - f) + RAMP[i + 1][j] * f));
      ctx.fillStyle = `rgb(${c[0]},${c[1]},${c[2]})`; ctx.fillRect(8 + k, 22, 1, 18);
    }
  } else {
    for (let k = 0; k < 240; k++) { const g = Math.round((k / 239) * 255); ctx.fillStyle = `rgb(${g},${g},${g})`; ctx.fillRect(8 + k, 22, 1, 18); }
  }
  ctx.fillStyle = "#000";
  ctx.fillText(fmt(lo, 3), 6, 54);
  const t = fmt(hi, 3);
  ctx.fillText(t, 248 - ctx.measureText(t).width, 54);
  $("legend-text").textContent = info.mode === "hillshade"
    ? `hillshade (sun from the north-west, 45 deg) of ${info.description || "band " + info.band}; heights ${fmt(lo, 3)} .. ${fmt(hi, 3)} (2nd - 98th percentile); transparent: nodata`
    : info.mode === "ramp" ? `${info.description || "band " + info.band}: colour from ${fmt(lo, 3)} to ${fmt(hi, 3)} (2nd - 98th percentile); transparent: nodata`
      : (info.dtype === "uint8" ? "image values as stored (uint8)" : `image stretched ${fmt(lo, 3)} .. ${fmt(hi, 3)} (2nd - 98th percentile)`);
  document.body.dataset.legend = "yes";
}

function drawLegend() {
  const c = $("legend-canvas"), ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  ctx.font = "11px sans-serif";
  if (S.view && S.view.kind === "raster" && S.rinfo) { drawRasterLegend(ctx, S.rinfo); return; }
  const label = S.view && S.view.kind === "table" ? "normalised residual" : "|v| / sigma (standardised)";
  ctx.fillStyle = "#000"; ctx.fillText(label, 4, 12);
  CLASSES.forEach(([, col, txt], k) => {
    ctx.fillStyle = col; ctx.fillRect(6, 20 + k * 16, 22, 10);
    ctx.fillStyle = "#000"; ctx.fillText(txt, 34, 29 + k * 16);
  });
  const y = 20 + CLASSES.length * 16 + 8;
  drawMarker(ctx, { z: null, flag: true, kind: "tie" }, 16, y);
  ctx.fillStyle = "#000"; ctx.fillText("flagged as a blunder", 34, y + 4);
  drawMarker(ctx, { z: 0, kind: "control" }, 16, y + 18); ctx.fillStyle = "#000"; ctx.fillText("control point", 34, y + 22);
  drawMarker(ctx, { z: 0, kind: "check" }, 130, y + 18); ctx.fillStyle = "#000"; ctx.fillText("check point", 148, y + 22);
  $("legend-text").textContent = `residual vectors x${fmt(S.exag, 1)}` +
    (S.view && S.view.kind === "layout" ? "; projection centres with their standard error ellipses (x, y; same factor); rays of the selected point" : "");
  document.body.dataset.legend = "yes";
}

// ------------------------------------------------------------------ detail
function rowTable(el, pairs, bad) {
  el.replaceChildren();
  for (const [k, v] of pairs) {
    const tr = document.createElement("tr");
    tr.dataset.key = k;
    if (bad && bad.has(k)) tr.className = "bad";
    const th = document.createElement("th"); th.textContent = k;
    const td = document.createElement("td"); td.textContent = fmt(v); td.dataset.value = v === null ? "" : String(v);
    tr.append(th, td); el.append(tr);
  }
}

async function trackOf(id) {
  const n = S.manifest.n_buckets;
  const b = crc32(id) % n;
  if (!S.buckets.has(b)) S.buckets.set(b, await getJSON(`api/tracks/${b}.json`));
  return S.buckets.get(b).tracks[id] || null;
}

async function select(id) {
  S.selected = id;
  $("detail").dataset.selected = id;
  $("detail-hint").textContent = id;
  const p = S.points.find((q) => q.id === id);
  rowTable($("row"), p ? p.row : [["id", id]], new Set(p && p.flag ? ["flag"] : []));
  $("point-row").replaceChildren();
  $("track").replaceChildren();
  S.track = null;
  if (S.manifest.kind === "block" && S.manifest.images.length) {
    const tr = await trackOf(id.split("@")[0]);
    S.track = tr;
    if (tr) {
      if (tr.point) rowTable($("point-row"), [["kind", tr.kind], ...Object.entries(tr.point), ["rays", tr.obs.length]]);
      for (const o of tr.obs) $("track").append(thumb(o, id.split("@")[0]));
    }
  }
  $("detail").dataset.ready = "yes";
  scheduleDraw();
}

function thumb(o, id) {
  const [i, col, row, vx, vy, , , flag, z] = o;
  const im = S.manifest.images[i];
  const div = document.createElement("div");
  div.className = "thumb" + (flag ? " flagged" : "");
  const cv = document.createElement("canvas");
  cv.width = 156; cv.height = 156;
  const cap = document.createElement("div");
  cap.textContent = `${im.name}  |v| ${fmt(Math.hypot(vx, vy), 3)} px  z ${fmt(z, 2)}${flag ? "  FLAGGED" : ""}`;
  div.append(cv, cap);
  div.addEventListener("click", () => openView({ kind: "image", n: i }, { at: [col, row], select: id }));
  const r = im.raster !== null ? S.manifest.rasters[im.raster] : null;
  const paint = () => {
    const ctx = cv.getContext("2d");
    ctx.fillStyle = "#ccd"; ctx.fillRect(0, 0, 156, 156);
    const k = 2;  // screen pixels per photo pixel: full resolution, magnified
    if (r) {
      const z0 = Math.min(r.max_level, staticLimit(r)), s = 2 ** (r.max_level - z0), span = r.tile * s;
      const x0 = col - 78 / k, y0 = row - 78 / k;
      for (let ty = Math.max(0, Math.floor(y0 / span)); ty <= Math.floor((y0 + 156 / k) / span); ty++) {
        for (let tx = Math.max(0, Math.floor(x0 / span)); tx <= Math.floor((x0 + 156 / k) / span); tx++) {
          if (tx * span >= r.width || ty * span >= r.height) continue;
          const t = requestTile(r, z0, tx, ty);
          if (!t.ok) { t.img.addEventListener("load", paint, { once: true }); continue; }
          const w = Math.min(span, r.width - tx * span), h = Math.min(span, r.height - ty * span);
          ctx.imageSmoothingEnabled = false;
          ctx.drawImage(t.img, (tx * span - 0.5 - x0) * k, (ty * span - 0.5 - y0) * k, w * k, h * k);
        }
      }
    }
    ctx.strokeStyle = "#00e5ff"; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(78, 68); ctx.lineTo(78, 88); ctx.moveTo(68, 78); ctx.lineTo(88, 78); ctx.stroke();
    ctx.strokeStyle = colourOf(z); ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(78, 78); ctx.lineTo(78 + S.exag * vx * k, 78 + S.exag * vy * k); ctx.stroke();
  };
  paint();
  return div;
}

function worstList() {
  const ol = $("worst-items");
  ol.replaceChildren();
  const pts = [...filtered()].sort((a, b) => Math.abs(b.z ?? -1) - Math.abs(a.z ?? -1)).slice(0, 30);
  for (const p of pts) {
    const li = document.createElement("li");
    li.textContent = `${p.id}  ${fmt(p.z, 2)}${p.flag ? "  flagged" : ""}`;
    li.addEventListener("click", () => { centreOn(p); select(p.id); });
    ol.append(li);
  }
}

function centreOn(p) {
  if (!placeable(p)) return;
  S.cam.cx = p.x; S.cam.cy = p.y;
  scheduleDraw();
}

// ------------------------------------------------------------------ views
function viewName(v) {
  if (v.kind === "layout") return "block layout";
  if (v.kind === "image") return `image ${S.manifest.images[v.n].name}`;
  if (v.kind === "raster") return `raster ${S.manifest.rasters[v.n].label}`;
  return `table ${S.manifest.tables[v.n].step}`;
}

function viewKey(v) { return v.kind === "layout" ? "layout" : `${v.kind}:${v.n}`; }

function views() {
  const m = S.manifest, out = [];
  if (m.kind === "block" && m.block_summary && Object.keys(m.block_summary).length) out.push({ kind: "layout" });
  m.rasters.forEach((r, n) => { if (r.role !== "photo") out.push({ kind: "raster", n }); });
  m.images.forEach((im, n) => out.push({ kind: "image", n }));
  m.tables.forEach((t, n) => out.push({ kind: "table", n }));
  return out;
}

async function loadPoints(v) {
  const m = S.manifest;
  if (v.kind === "image") {
    if (!S.obs.has(v.n)) S.obs.set(v.n, await getJSON(`api/obs/${v.n}.json`));
    const o = S.obs.get(v.n);
    return o.id.map((id, k) => ({
      id, x: o.col[k], y: o.row[k], vx: o.vx[k], vy: o.vy[k], z: o.z[k], flag: !!o.flag[k], kind: o.kind[k], i: v.n,
      row: [["image", o.image], ["id", id], ["kind", o.kind[k]], ["col", o.col[k]], ["row", o.row[k]],
        ["vx", o.vx[k]], ["vy", o.vy[k]], ["|v|", Math.hypot(o.vx[k], o.vy[k])], ["sigma", o.sigma[k]],
        ["standardised", o.z[k]], ["weight", o.weight[k]], ["flag", o.flag[k]],
        ...(o.redundancy ? [["redundancy", o.redundancy[k]]] : [])],
    }));
  }
  if (v.kind === "table") {
    if (!S.tables.has(v.n)) S.tables.set(v.n, await getJSON(`api/table/${v.n}.json`));
    const t = S.tables.get(v.n), cols = t.columns, comps = t.components.length ? t.components : cols.filter((c) => /^d/.test(c));
    const ix = (name) => cols.indexOf(name);
    const [io0, io1, ic0, ic1, inn, iout, ichk] = ["observed_0", "observed_1", comps[0], comps[1], "normalised", "outlier", "check"].map(ix);
    const [icl, irl] = ["col_left", "row_left"].map(ix);
    const placed = icl >= 0;  // a one-component table (y-parallax) at the left image's tie points
    v.placed = placed;
    return t.rows.map((r) => {
      const id = String(r[0]);
      const img = id.includes("@") ? id.split("@")[1] : "";
      if (placed) {
        return {
          id, x: r[icl], y: r[irl], vx: 0, vy: ic0 >= 0 ? r[ic0] : null, z: inn >= 0 ? r[inn] : null,
          flag: iout >= 0 && r[iout] === 1, kind: ichk >= 0 && r[ichk] === 1 ? "check" : "tie", image: img,
          row: cols.map((c, k) => [c, r[k]]),
        };
      }
      return {
        id, x: r[io0], y: io1 >= 0 ? r[io1] : 0, vx: ic0 >= 0 ? r[ic0] : null, vy: ic1 >= 0 ? r[ic1] : null,
        z: inn >= 0 ? r[inn] : null, flag: iout >= 0 && r[iout] === 1, kind: ichk >= 0 && r[ichk] === 1 ? "check" : "tie", image: img,
        row: cols.map((c, k) => [c, r[k]]),
      };
    }).filter((p) => !S.imageFilter || p.image === S.imageFilter);
  }
  if (v.kind === "layout") {
    if (!S.layout) S.layout = await getJSON("api/layout.json");
    return S.layout.marks.map((mk) => ({
      id: mk.id, x: mk.x, y: mk.y, vx: mk.v[0], vy: mk.v[1], z: mk.normalised, flag: mk.outlier === 1, kind: mk.kind,
      row: [["id", mk.id], ["kind", mk.kind], ["x", mk.x], ["y", mk.y], ...mk.v.map((d, k) => [["dX", "dY", "dZ"][k], d]),
        ["normalised", mk.normalised], ["outlier", mk.outlier], ["table", m.tables[mk.table].step]],
    }));
  }
  return [];
}

async function openView(v, opts = {}) {
  S.view = v;
  document.body.dataset.state = "loading";
  document.body.dataset.view = viewKey(v);
  $("view-select").value = viewKey(v);
  setStatus(`loading ${viewName(v)}`);
  S.points = await loadPoints(v);
  const m = S.manifest;
  S.rinfo = null;
  if (v.kind === "raster") {  // the legend's numbers: not awaited, the tiles come first
    getJSON(`api/raster/${v.n}.json`).then((info) => { if (S.view === v) { S.rinfo = info; drawLegend(); } })
      .catch((err) => { document.body.dataset.error = String(err); });
  }
  if (v.kind === "layout") {
    S.cam.yUp = true;
    const xs = [], ys = [];
    for (const im of S.layout.images) {
      xs.push(im.position[0]); ys.push(im.position[1]);
      for (const [x, y] of im.footprint || []) { xs.push(x); ys.push(y); }
    }
    fit(...extent(xs, ys));
  } else if (v.kind === "table") {
    const t = S.tables.get(v.n);
    v.units = v.placed ? "px" : t.units;
    S.cam.yUp = !v.placed && t.units !== "px";
    const xs = S.points.filter(placeable).map((p) => p.x), ys = S.points.filter(placeable).map((p) => p.y);
    if (xs.length) fit(...extent(xs, ys)); else fit(0, 0, 1, 1);
  } else {
    S.cam.yUp = false;
    v.units = "px";
    const r = rasterOf();
    const w = r ? r.width : m.images[v.n].width || 1, h = r ? r.height : m.images[v.n].height || 1;
    fit(-0.5, -0.5, w - 0.5, h - 0.5);
  }
  if (opts.at) {
    S.cam.cx = opts.at[0]; S.cam.cy = opts.at[1];
    if (opts.full) S.cam.scale = 2;
  }
  drawLegend();
  worstList();
  figuresFor(v);
  draw();
  if (opts.select) await select(opts.select);
  setStatus(`${viewName(v)}: ${S.points.length} points`);
  if (!document.body.dataset.readyMs) document.body.dataset.readyMs = String(Math.round(performance.now()));
  document.body.dataset.state = "ready";
}

function figuresFor(v) {
  const ul = $("figure-list");
  ul.replaceChildren();
  const add = (title, href) => {
    const li = document.createElement("li"), a = document.createElement("a");
    a.href = `files/${href}`; a.textContent = title; a.target = "_blank"; a.rel = "noopener";
    li.append(a); ul.append(li);
  };
  if (v.kind === "table") for (const [k, f] of Object.entries(S.manifest.tables[v.n].figures)) add(`${S.manifest.tables[v.n].step}: ${k}`, f);
  for (const f of S.manifest.figures) add(f.title, f.href);
  for (const r of S.manifest.reports) add(`${r.title} (static report page)`, r.href);
}

function notes() {
  const el = $("note-list"), m = S.manifest;
  el.replaceChildren();
  const add = (title, obj) => {
    const h = document.createElement("h3"); h.textContent = title;
    const pre = document.createElement("pre"); pre.textContent = typeof obj === "string" ? obj : JSON.stringify(obj, null, 1);
    el.append(h, pre);
  };
  if (m.block_summary && Object.keys(m.block_summary).length) add("block", m.block_summary);
  if (m.datum && m.datum.length) add("datum", m.datum.join("\n"));
  for (const n of m.notes) add(n.file, n.summary);
  if (m.static) add("static export", m.static.note);
}

// ------------------------------------------------------------------ input
function hitTest(sx, sy) {
  let best = null, bd = 9 * 9;
  for (const p of filtered()) {
    if (!placeable(p)) continue;
    const [px, py] = toScreen(p.x, p.y);
    const d = (px - sx) ** 2 + (py - sy) ** 2;
    if (d <= bd) { bd = d; best = p; }
  }
  return best;
}

function setupInput() {
  const c = canvas();
  let drag = null, moved = false;
  c.addEventListener("mousedown", (e) => { drag = [e.offsetX, e.offsetY]; moved = false; });
  c.addEventListener("mousemove", (e) => {
    if (!drag) {
      const [x, y] = toWorld(e.offsetX, e.offsetY);
      if (S.view) setStatus(`${viewName(S.view)}  x ${fmt(x, 2)}  y ${fmt(y, 2)}  level ${document.body.dataset.level ?? "-"}`);
      return;
    }
    const dx = e.offsetX - drag[0], dy = e.offsetY - drag[1];
    if (Math.abs(dx) + Math.abs(dy) > 2) moved = true;
    S.cam.cx -= dx / S.cam.scale; S.cam.cy -= (S.cam.yUp ? -1 : 1) * dy / S.cam.scale;
    drag = [e.offsetX, e.offsetY];
    scheduleDraw();
  });
  window.addEventListener("mouseup", () => { drag = null; });
  c.addEventListener("click", (e) => {
    if (moved) return;
    const p = hitTest(e.offsetX, e.offsetY);
    if (p) { select(p.id); return; }
    if (S.view && S.view.kind === "layout") {
      for (const im of S.layout.images) {
        const [sx, sy] = toScreen(im.position[0], im.position[1]);
        if ((sx - e.offsetX) ** 2 + (sy - e.offsetY) ** 2 < 49) { openView({ kind: "image", n: im.i }); return; }
      }
      const P = S.layout.points;  // a tie point of the plan: its track and rays
      let best = -1, bd = 16;
      for (let k = 0; P && k < P.x.length; k++) {
        const [sx, sy] = toScreen(P.x[k], P.y[k]);
        const d = (sx - e.offsetX) ** 2 + (sy - e.offsetY) ** 2;
        if (d < bd) { bd = d; best = k; }
      }
      if (best >= 0) select(P.id[best]);
    }
  });
  c.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [wx, wy] = toWorld(e.offsetX, e.offsetY);
    const f = Math.exp(-e.deltaY * 0.0015);
    S.cam.scale = Math.min(64, Math.max(1e-6, S.cam.scale * f));
    const [nx, ny] = toWorld(e.offsetX, e.offsetY);
    S.cam.cx += wx - nx; S.cam.cy += wy - ny;
    scheduleDraw();
  }, { passive: false });
  new ResizeObserver(() => {
    // setting a canvas' size clears it, even to the same size: only on a real change, and redraw at once
    if (c.width === c.clientWidth && c.height === c.clientHeight) return;
    c.width = c.clientWidth; c.height = c.clientHeight;
    draw();
  }).observe(c);
  c.width = c.clientWidth || 800; c.height = c.clientHeight || 600;
  $("exag").addEventListener("input", () => { S.exag = 10 ** Number($("exag").value); $("exag-val").textContent = `x${fmt(S.exag, 1)}`; drawLegend(); scheduleDraw(); });
  $("worst").addEventListener("change", () => { S.worst = Math.max(0, Number($("worst").value) || 0); worstList(); scheduleDraw(); });
  $("flag").addEventListener("change", () => { S.flag = $("flag").value; worstList(); scheduleDraw(); });
  $("image-filter").addEventListener("change", () => {
    S.imageFilter = $("image-filter").value;
    const v = S.view;
    if (v && v.kind === "table") openView(v);
    else if (S.imageFilter) {
      const k = S.manifest.images.findIndex((im) => im.name === S.imageFilter);
      if (k >= 0) openView({ kind: "image", n: k });
    }
  });
  $("view-select").addEventListener("change", () => {
    const v = views().find((w) => viewKey(w) === $("view-select").value);
    if (v) openView(v);
  });
}

// crc32 of the UTF-8 id: the server's track bucket (rectify.view.data.bucket_of)
const CRC = (() => { const t = new Uint32Array(256); for (let n = 0; n < 256; n++) { let c = n; for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1; t[n] = c >>> 0; } return t; })();
function crc32(s) {
  let c = 0xffffffff;
  for (const b of new TextEncoder().encode(s)) c = CRC[(c ^ b) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

// ------------------------------------------------------------------ start
function parseView(text) {
  if (!text) return null;
  if (text === "layout") return { kind: "layout" };
  const [kind, rest] = text.split(":");
  if (kind === "image" && rest !== undefined && !/^\d+$/.test(rest)) {
    const n = S.manifest.images.findIndex((im) => im.name === rest);
    return n >= 0 ? { kind, n } : null;
  }
  const n = Number(rest);
  const size = { image: S.manifest.images.length, raster: S.manifest.rasters.length, table: S.manifest.tables.length }[kind];
  const ok = size !== undefined && Number.isInteger(n) && n >= 0 && n < size;
  if (ok && kind === "raster" && S.manifest.rasters[n].role === "photo") return { kind: "image", n: S.manifest.images.findIndex((im) => im.raster === n) };
  return ok ? { kind, n } : null;
}

async function main() {
  setupInput();
  S.manifest = await getJSON("api/manifest.json");
  const m = S.manifest;
  $("title").textContent = `${m.title} (${m.kind})`;
  document.title = `rectify view: ${m.title}`;
  const sel = $("view-select");
  for (const v of views()) {
    const o = document.createElement("option"); o.value = viewKey(v); o.textContent = viewName(v); sel.append(o);
  }
  for (const im of m.images) {
    const o = document.createElement("option"); o.value = im.name; o.textContent = `${im.name} (${im.n_obs}, ${im.n_flagged} flagged)`;
    $("image-filter").append(o);
  }
  notes();
  const p = S.params;
  if (p.get("exag")) { S.exag = Number(p.get("exag")) || S.exag; $("exag").value = String(Math.log10(S.exag)); }
  $("exag-val").textContent = `x${fmt(S.exag, 1)}`;
  if (p.get("worst")) { S.worst = Math.max(0, Number(p.get("worst")) || 0); $("worst").value = String(S.worst); }
  if (p.get("flag") && [...$("flag").options].some((o) => o.value === p.get("flag"))) { S.flag = p.get("flag"); $("flag").value = S.flag; }
  const all = views();
  if (!all.length) { setStatus("nothing to show in this folder"); document.body.dataset.state = "ready"; document.body.dataset.view = "none"; return; }
  const asked = parseView(p.get("view"));
  const v = asked && all.some((w) => viewKey(w) === viewKey(asked)) ? asked : all[0];
  const opts = {};
  if (p.get("at")) { opts.at = p.get("at").split(",").map(Number); opts.full = p.get("zoom") === "full"; }
  if (p.get("select")) opts.select = p.get("select");
  await openView(v, opts);
  if (p.get("click")) {
    const id = p.get("click"), q = S.points.find((pt) => pt.id === id);
    if (q) {
      centreOn(q); draw();
      const [sx, sy] = toScreen(q.x, q.y), rect = canvas().getBoundingClientRect();
      canvas().dispatchEvent(new MouseEvent("click", { clientX: rect.left + sx, clientY: rect.top + sy, bubbles: true }));
    }
  }
}

// for scripts driving the page (the browser test): where a point is on the screen, in CSS pixels of the page
window.rectifyView = {
  screenOf(id) {
    const p = S.points.find((q) => q.id === id);
    if (!p || !placeable(p)) return null;
    const [sx, sy] = toScreen(p.x, p.y), rect = canvas().getBoundingClientRect();
    return [rect.left + sx, rect.top + sy];
  },
  scale() { return S.cam.scale; },  // screen pixels per image pixel (or per ground unit)
  centreOn(id) { const p = S.points.find((q) => q.id === id); if (p) { centreOn(p); draw(); } return !!p; },
};

main().catch((err) => { document.body.dataset.state = "failed"; document.body.dataset.error = String(err); setStatus(String(err)); console.error(err); });

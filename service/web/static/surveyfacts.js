// What a job's survey.json says (the survey stage's result, pipeline/survey), read defensively: any key may be
// missing or null, and a fact is shown only when its number is there. Formatting only; no DOM.

const SIGNIFICANT = 3;

const isNum = (v) => typeof v === "number" && Number.isFinite(v);
const obj = (v) => (v && typeof v === "object" ? v : {});

// 3 significant digits, plain notation: 0.0021, 31.2, 12300
export function num(v) {
  return String(Number(v.toPrecision(SIGNIFICANT)));
}

// heights and lengths in the frame's units: metres shown in mm, cm or m; arbitrary scene units as "units"
export function length(v, metric) {
  if (!metric) return `${num(v)} units`;
  const a = Math.abs(v);
  if (a > 0 && a < 0.01) return `${num(v * 1000)} mm`;
  if (a > 0 && a < 1) return `${num(v * 100)} cm`;
  return `${num(v)} m`;
}

// the products are in metres when the stage says so (grid or frame units "m"), or when it found a metric scale
export function isMetric(survey) {
  const units = obj(survey.grid).units ?? obj(survey.frame).units;
  return units === undefined || units === null ? isNum(obj(survey.scale).metres_per_unit) : units === "m";
}

function scaleText(scale, metric) {
  if (!Object.keys(scale).length) return null; // survey.json says nothing of the scale
  if (!isNum(scale.metres_per_unit)) return metric ? null : "none found: sizes are in the model's own units";
  const how = [scale.source && `from ${String(scale.source).replace(/_/g, " ")}`,
    isNum(scale.spread) && `spread ${num(scale.spread * 100)} %`,
    isNum(scale.frames) && `${scale.frames} frames`].filter(Boolean);
  return `${num(scale.metres_per_unit)} m per unit${how.length ? ` (${how.join(", ")})` : ""}`;
}

function frameText(frame) {
  const name = frame.crs_name || frame.crs;
  if (!name) return null;
  return frame.crs && frame.crs_name && frame.crs !== frame.crs_name ? `${frame.crs_name} (${frame.crs})` : name;
}

// the 2-98 % height range (robust to a stray cell), with the whole span beside it
function heightRange(h) {
  return isNum(h.robust_range) ? h.robust_range : h.range;
}

function heightText(h, metric) {
  if (!isNum(heightRange(h))) return null;
  const span = isNum(h.min) && isNum(h.max) ? ` (${length(h.min, metric)} to ${length(h.max, metric)})` : "";
  return `${length(heightRange(h), metric)} (2-98 %)${span}`;
}

// [{key, label, text, value}]: value is the number (or string) survey.json holds, text what a person reads
export function facts(survey) {
  const s = obj(survey), grid = obj(s.grid), frame = obj(s.frame), scale = obj(s.scale);
  const terrain = obj(s.terrain), height = obj(terrain.height);
  const metric = isMetric(s);
  const area = metric ? "m²" : "units²";
  const georef = frame.georeferenced === true
    ? `yes${isNum(frame.gps_residual_m) ? ` (GPS fit ${length(frame.gps_residual_m, true)})` : ""}`
    : frame.georeferenced === false ? "no" : null;
  const rows = [
    ["gsd", "ground resolution", isNum(grid.gsd) ? `${length(grid.gsd, metric)} per pixel` : null, grid.gsd],
    ["crs", "coordinate system", frameText(frame), frame.crs || frame.crs_name],
    ["georeferenced", "georeferenced", georef, frame.georeferenced],
    ["area", "area", isNum(grid.area) ? `${num(grid.area)} ${area}` : null, grid.area],
    ["rugosity", "rugosity", isNum(terrain.rugosity) ? num(terrain.rugosity) : null, terrain.rugosity],
    ["height", "height range", heightText(height, metric), heightRange(height)],
    ["scale", "metric scale", scaleText(scale, metric), scale.metres_per_unit],
    ["size", "mosaic", isNum(grid.width) && isNum(grid.height) ? `${grid.width} × ${grid.height} px` : null,
      isNum(grid.width) ? `${grid.width}x${grid.height}` : null],
  ];
  return rows.filter(([, , text]) => text).map(([key, label, text, value]) => ({ key, label, text, value }));
}

// the stage's own explanations (why there is no metric scale, why not georeferenced), as it wrote them
export function notes(survey) {
  const s = obj(survey);
  return [obj(s.frame).note, obj(s.scale).note].filter((n) => typeof n === "string" && n.trim());
}

// the ground size of one pixel of a preview `previewWidth` pixels wide (previews share the mosaic's footprint)
export function groundPerPixel(survey, previewWidth) {
  const grid = obj(obj(survey).grid);
  const b = grid.bounds;
  if (Array.isArray(b) && b.length === 4 && b.every(isNum) && b[2] > b[0]) return (b[2] - b[0]) / previewWidth;
  if (isNum(grid.gsd) && isNum(grid.width)) return (grid.gsd * grid.width) / previewWidth;
  return null;
}

// the ground point (x, y) of preview pixel (u, v): row 0 is the north (max y) edge
export function groundAt(survey, u, v, previewWidth, previewHeight) {
  const b = obj(obj(survey).grid).bounds;
  if (!Array.isArray(b) || b.length !== 4 || !b.every(isNum)) return null;
  return { x: b[0] + (u / previewWidth) * (b[2] - b[0]), y: b[3] - (v / previewHeight) * (b[3] - b[1]) };
}

// the longest of 1, 2, 5 × 10^k not over `most` (a scale bar's length)
export function niceLength(most) {
  const p = 10 ** Math.floor(Math.log10(most));
  return [5, 2, 1].map((m) => m * p).find((v) => v <= most) ?? p;
}

// The nlpsf page: calculator, curves and fresh simulations over the REST API (/api/v1).
// Plain JavaScript and the vendored uPlot; no build step, no network beyond this server.
"use strict";

const API = "api/v1";
// Okabe & Ito's colour-blind-safe palette: the paper's four bands get four far-apart hues.
const BAND_COLORS = {
  R062: "#E69F00", Z087: "#56B4E9", Y106: "#0072B2", J129: "#009E73",
  H158: "#D55E00", F184: "#CC79A7", W146: "#000000", K213: "#8C6D00",
};
// Several fresh simulations (one per β) on one plot.
const SERIES_COLORS = ["#c00000", "#0072B2", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#8C6D00"];
const METRIC_LABEL = { size: "ΔR/R", e1: "Δe₁", e2: "Δe₂", e: "|Δe|" };
const METRIC_KEY = { size: "dR_over_R", e1: "de1", e2: "de2" };
const state = { meta: null, paper: null, plots: {}, exports: {}, lastSimulation: null, polling: null };

class ApiError extends Error {
  // errors: [{field, msg}] -- every bad field the server (or the page's own check) found.
  constructor(message, field, status, errors = []) {
    super(message);
    this.field = field;
    this.status = status;
    this.errors = errors;
  }
}

async function api(path, options = {}) {
  const { followJob: follow = false, ...fetchOptions } = options;
  const response = await fetch(`${API}${path}`, {
    ...fetchOptions,
    headers: { "Content-Type": "application/json", ...(fetchOptions.headers || {}) },
  });
  let body = null;
  try {
    body = await response.json();
  } catch (_) {
    body = null;
  }
  if (!response.ok) {
    const message = body && (body.detail || body.message) ? (typeof body.detail === "string" ? body.detail : body.message)
      : `the server answered ${response.status}`;
    throw new ApiError(message, body ? body.field : null, response.status, (body && Array.isArray(body.errors)) ? body.errors : []);
  }
  if (follow && response.status === 202 && body && body.id) {
    // A solve or impact report that needs a simulation became a job: follow it to its answer.
    return waitForJob(response.headers.get("Location") || `${API}/simulations/${body.id}`);
  }
  return body;
}

async function waitForJob(location) {
  for (;;) {
    await new Promise((resolve) => setTimeout(resolve, 500));
    const response = await fetch(location);
    const job = await response.json().catch(() => null);
    if (!response.ok || !job) {
      throw new ApiError((job && job.detail) || `the server answered ${response.status}`, null, response.status, []);
    }
    if (job.status === "done") return job.result;
    if (["failed", "cancelled", "interrupted"].includes(job.status)) {
      const error = job.error || {};
      throw new ApiError(error.message || `the simulation was ${job.status}`, error.field || null, 500, []);
    }
  }
}

// ---- formatting -------------------------------------------------------------------------

function fmt(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "n/a";
  const a = Math.abs(x);
  if (a !== 0 && (a >= 1e5 || a < 1e-3)) {
    // "1e-4", "2.5e-7": no trailing zeros, the same short form as the axes.
    const [mantissa, exponent] = x.toExponential(digits - 1).split("e");
    return `${Number(mantissa)}e${exponent}`;
  }
  return Number(x.toPrecision(digits)).toString();
}

// One format per axis: plain decimals where they read well, otherwise the same short exponent
// form everywhere ("2.5e-7", "1e+4"), never a mix of 10000 and 1.00e+6 on one axis.
function shortExp(x) {
  if (x === 0) return "0";
  const [mantissa, exponent] = x.toExponential(2).split("e");
  return `${Number(mantissa)}e${exponent}`;
}

function axisFormatter(logScale) {
  return (u, splits) => {
    const finite = splits.filter((v) => v !== null && Number.isFinite(v));
    const big = Math.max(...finite.map(Math.abs));
    const small = Math.min(...finite.filter((v) => v !== 0).map(Math.abs));
    const exponent = big >= 1e4 || (small < 1e-2 && small > 0);
    // On a log axis label 1, 2 and 5 per decade over a short range, only the decades over a long one.
    const decades = finite.length ? Math.log10(big / (small || big)) : 0;
    const keep = (v) => {
      if (!logScale) return true;
      const mantissa = Math.round(v / 10 ** Math.floor(Math.log10(Math.abs(v)) + 1e-9));
      return decades > 2.5 ? mantissa === 1 : [1, 2, 5].includes(mantissa);
    };
    const decimals = Math.max(0, ...finite.map((v) => {
      const text = String(Number(v.toPrecision(6)));
      return text.includes(".") ? text.split(".")[1].length : 0;
    }));
    return splits.map((v) => {
      if (v === null || !Number.isFinite(v) || !keep(v)) return "";
      return exponent ? shortExp(v) : v.toFixed(Math.min(decimals, 4));
    });
  };
}

// On a log axis, ticks and grid lines at 1, 2, 5 per decade over a short range, only decades over a long one.
function logFilter(logScale) {
  if (!logScale) return undefined;
  return (u, splits) => {
    const finite = splits.filter((v) => v !== null && v > 0);
    const decades = finite.length ? Math.log10(Math.max(...finite) / Math.min(...finite)) : 0;
    return splits.map((v) => {
      if (v === null || !(v > 0)) return null;
      const mantissa = Math.round(v / 10 ** Math.floor(Math.log10(v) + 1e-9));
      return (decades > 2.5 ? mantissa === 1 : [1, 2, 5].includes(mantissa)) ? v : null;
    });
  };
}

// The same choice for the labels, the ticks and the grid lines (uPlot filters each on its own).
function logSplits(logScale) {
  const filter = logFilter(logScale);
  return filter ? { filter, ticks: { filter }, grid: { filter } } : {};
}

function plusMinus(value, error) {
  return error === null || error === undefined ? fmt(value) : `${fmt(value)} ± ${fmt(error, 2)}`;
}

function conditionsText(c, extra = {}) {
  if (!c) return "";
  const parts = [
    `${c.band} · SCA ${c.sca}`,
    `exposure ${fmt(c.exptime_s ?? c.exptime)} s`,
    c.beta0 !== undefined ? `β₀ = ${fmt(c.beta0)} /e⁻` : null,
    c.full_well_e !== undefined ? `full well ${fmt(c.full_well_e)} e⁻` : null,
    `fidelity ${c.fidelity}`,
    c.realizations !== undefined ? `${c.realizations} realizations` : null,
    c.oversampling !== undefined ? `N = ${c.oversampling}, ${c.stamp}×${c.stamp}` : null,
    c.ramp ? `up the ramp: ${c.ramp.description}` : null,
    ...Object.entries(extra).map(([k, v]) => `${k} ${v}`),
  ];
  return parts.filter(Boolean).join(" · ");
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (ch) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[ch]);
}

// A number typed by the user, or the raw text so that the server names the field it cannot read.
function numberOrText(text) {
  const trimmed = String(text).trim();
  if (trimmed === "") return null;
  const value = Number(trimmed);
  return Number.isFinite(value) ? value : trimmed;
}

function listOf(text) {
  return String(text).split(/[\s,;]+/).filter(Boolean).map(numberOrText);
}

function fillSelect(select, values, chosen, label = (v) => v) {
  select.innerHTML = values.map((v) => `<option value="${escapeHtml(v)}">${escapeHtml(label(v))}</option>`).join("");
  select.value = String(chosen);
}

// Shows every bad field at once (the server's errors list, or the page's own check) and marks each input.
function showError(box, form, error) {
  const errors = (error.errors || []).filter((e) => e && (e.field || e.msg));
  if (errors.length > 1) {
    box.innerHTML = `<div>${errors.length} fields need a look:</div><ul>${errors.map((e) =>
      `<li data-field="${escapeHtml(e.field || "")}">${escapeHtml(e.field ? `${e.field}: ${e.msg}` : e.msg)}</li>`).join("")}</ul>`;
  } else {
    box.textContent = error.message;
  }
  box.hidden = false;
  if (form) {
    form.querySelectorAll("[aria-invalid]").forEach((el) => el.removeAttribute("aria-invalid"));
    for (const field of [error.field, ...errors.map((e) => e.field)]) {
      if (field && form.elements[field] && form.elements[field].setAttribute) form.elements[field].setAttribute("aria-invalid", "true");
    }
  }
}

function clearError(box, form) {
  box.hidden = true;
  box.textContent = "";
  if (form) form.querySelectorAll("[aria-invalid]").forEach((el) => el.removeAttribute("aria-invalid"));
}

// ---- plots --------------------------------------------------------------------------------

function lineSeries(label, color, dash) {
  return { label, stroke: color, width: 2, spanGaps: true, dash, points: { show: false } };
}

function pointSeries(label, color, size = 8) {
  return { label, stroke: color, fill: color, width: 0, paths: () => null, points: { show: true, size, fill: color } };
}

// Draw (or redraw) plot `name` in its container. `columns` = [{label, x, y, err, fid, series}], joined on x;
// err: 1σ statistical uncertainty per point, fid: relative fidelity uncertainty (both drawn as a band).
// `markers` = [{x, label, color}]: dashed vertical lines (e.g. saturation limits), kept in view.
// `shades` = [{from, to, label, color, hatch}]: x ranges shaded behind the curves.
function drawPlot(name, { xLabel, yLabel, columns, logX = false, logY = false, title, markers = [], shades = [], cursorAt = null }) {
  const el = document.getElementById(`plot-${name}`);
  const usable = columns.map((c) => {
    const keep = c.x.map((x, i) => x !== null && c.y[i] !== null && (!logX || x > 0) && (!logY || c.y[i] > 0));
    const err = c.err ? c.err.filter((_, i) => keep[i]) : null;
    return { ...c, x: c.x.filter((_, i) => keep[i]), y: c.y.filter((_, i) => keep[i]), err };
  }).filter((c) => c.x.length > 0);
  state.exports[name] = { title, xLabel, yLabel, columns: usable, markers, shades };
  if (state.plots[name]) {
    state.plots[name].destroy();
    delete state.plots[name];
  }
  el.innerHTML = "";
  if (usable.length === 0) {
    el.innerHTML = '<p class="muted">nothing to plot for these conditions</p>';
    return;
  }
  const data = uPlot.join(usable.map((c) => {
    const order = c.x.map((_, i) => i).sort((a, b) => c.x[a] - c.x[b]);
    return [order.map((i) => c.x[i]), order.map((i) => c.y[i])];
  }));
  // Each series' 1σ half-width at each joined x (statistical and fidelity in quadrature), for the bands.
  const halfWidths = usable.map((c) => {
    const byX = new Map(c.x.map((x, i) => [x, total(c, i)]));
    return data[0].map((x) => (byX.has(x) ? byX.get(x) : null));
  });
  // Without a cursor the legend shows the values at this x (the answer, or the middle of the data).
  const xs = data[0];
  const target = cursorAt ?? xs[Math.floor(xs.length / 2)];
  const defaultIdx = xs.reduce((best, x, i) => (Math.abs(x - target) < Math.abs(xs[best] - target) ? i : best), 0);
  const rangeWith = markers.length || shades.length;
  // Limits stay in view; a shade reaches as far as the data (it is clipped to the plot).
  const edges = [...markers.map((m) => m.x), ...shades.map((s) => s.to)].filter(Number.isFinite);
  const options = {
    width: Math.max(280, el.clientWidth || 800),
    height: 320,
    scales: {
      x: { time: false, distr: logX ? 3 : 1,
        ...(rangeWith && !logX ? { range: (u, lo, hi) => [Math.min(lo, ...edges.map((x) => x - 0.25)),
          Math.max(hi, ...markers.map((m) => m.x + 0.25))] } : {}) },
      y: { distr: logY ? 3 : 1 },
    },
    // Before the series, so that a point on a limit stays visible.
    hooks: { drawClear: [(u) => { drawShades(u, shades); drawMarkers(u, markers); drawBands(u, usable, halfWidths); }] },
    axes: [
      { label: xLabel, values: axisFormatter(logX), space: 60, ...logSplits(logX) },
      { label: yLabel, values: axisFormatter(logY), size: 72, space: 36, ...logSplits(logY) },
    ],
    series: [{ label: xLabel, value: (u, v, si, i) => fmt(i == null ? u.data[0][defaultIdx] : v) },
      ...usable.map((c, k) => {
        // Hover shows each value with its uncertainty, looked up by x (the joined data has gaps).
        const index = new Map(c.x.map((x, i) => [x, i]));
        return { ...c.series, value: (u, v, si, i) => {
          let where = "";
          if (i == null) {
            // No cursor: this series' value nearest the default x (the joined data has gaps).
            i = nearestDefined(u.data[si], defaultIdx);
            if (i == null) return "–";
            v = u.data[si][i];
            if (i !== defaultIdx) where = ` (at ${fmt(u.data[0][i])})`;
          }
          if (v == null) return "–";
          const j = index.get(u.data[0][i]);
          return (c.describe ? c.describe(v, j) : describeValue(c, v, j)) + where;
        } };
      })],
    legend: { live: true },
    cursor: { points: { size: 8 } },
  };
  state.plots[name] = new uPlot(options, data, el);
  state.plots[name].defaultIdx = defaultIdx;
  state.plots[name].halfWidths = halfWidths;
}

function nearestDefined(values, start) {
  for (let d = 0; d < values.length; d++) {
    if (values[start - d] != null) return start - d;
    if (values[start + d] != null) return start + d;
  }
  return null;
}

function total(c, i) {
  const stat = c.err && c.err[i] != null ? c.err[i] : 0;
  const fid = c.fid != null ? Math.abs(c.y[i]) * c.fid : 0;
  return stat || fid ? Math.hypot(stat, fid) : null;
}

// "value ± stat (stat) ± fid (fidelity)": the same two parts the calculator quotes.
function describeValue(c, v, j) {
  const stat = j != null && c.err ? c.err[j] : null;
  const fid = c.fid != null ? Math.abs(v) * c.fid : null;
  if (stat == null && fid == null) return fmt(v);
  const parts = [];
  if (stat != null) parts.push(`± ${fmt(stat, 2)} stat`);
  if (fid != null) parts.push(`± ${fmt(fid, 2)} fidelity`);
  return `${fmt(v)} ${parts.join(" ")}`;
}

function drawBands(u, columns, halfWidths) {
  const ctx = u.ctx;
  columns.forEach((c, k) => {
    if (c.band === false || !halfWidths[k].some((h) => h)) return;
    const si = k + 1;
    const top = [];
    const bottom = [];
    u.data[0].forEach((x, i) => {
      const y = u.data[si][i];
      const h = halfWidths[k][i];
      if (y == null || h == null) return;
      const low = u.scales.y.distr === 3 ? Math.max(y - h, y * 1e-3) : y - h;
      top.push([u.valToPos(x, "x", true), u.valToPos(y + h, "y", true)]);
      bottom.push([u.valToPos(x, "x", true), u.valToPos(low, "y", true)]);
    });
    if (top.length < 2) return;
    ctx.save();
    ctx.beginPath();
    top.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    bottom.reverse().forEach(([x, y]) => ctx.lineTo(x, y));
    ctx.closePath();
    ctx.globalAlpha = 0.2;
    ctx.fillStyle = c.series.stroke || "#888";
    ctx.fill();
    ctx.restore();
  });
}

function drawShades(u, shades) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  shades.forEach((s, i) => {
    const lo = Math.max(u.bbox.left, u.valToPos(s.from, "x", true));
    const hi = Math.min(u.bbox.left + u.bbox.width, u.valToPos(s.to, "x", true));
    if (!(hi > lo)) return;
    ctx.save();
    ctx.beginPath();
    ctx.rect(lo, u.bbox.top, hi - lo, u.bbox.height);
    ctx.clip();
    ctx.fillStyle = s.color;
    ctx.fillRect(lo, u.bbox.top, hi - lo, u.bbox.height);
    if (s.hatch) {
      ctx.strokeStyle = s.hatch;
      ctx.lineWidth = ratio;
      for (let x = lo - u.bbox.height; x < hi; x += 8 * ratio) {
        ctx.beginPath();
        ctx.moveTo(x, u.bbox.top + u.bbox.height);
        ctx.lineTo(x + u.bbox.height, u.bbox.top);
        ctx.stroke();
      }
    }
    ctx.restore();
    // The label outside the clip: a narrow range still names itself.
    ctx.save();
    ctx.fillStyle = "#333";
    ctx.font = `${11 * ratio}px sans-serif`;
    ctx.fillText(s.label, lo + 4 * ratio, u.bbox.top + u.bbox.height - (8 + 14 * i) * ratio);
    ctx.restore();
  });
}

function drawMarkers(u, markers) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  markers.forEach((m, i) => {
    const x = u.valToPos(m.x, "x", true);
    if (!Number.isFinite(x)) return;
    ctx.save();
    ctx.strokeStyle = m.color;
    ctx.fillStyle = m.color;
    ctx.lineWidth = 1.5 * ratio;
    ctx.setLineDash([6 * ratio, 4 * ratio]);
    ctx.beginPath();
    ctx.moveTo(x, u.bbox.top);
    ctx.lineTo(x, u.bbox.top + u.bbox.height);
    ctx.stroke();
    ctx.font = `${11 * ratio}px sans-serif`;
    ctx.fillText(m.label, x + 4 * ratio, u.bbox.top + (12 + 14 * i) * ratio);
    ctx.restore();
  });
}

function exportCsv(name) {
  const plot = state.exports[name];
  if (!plot) return;
  const lines = [`# ${plot.title.replace(/\n/g, " ")}`, ""];
  lines[1] = `series,${plot.xLabel},${plot.yLabel},uncertainty`;
  for (const c of plot.columns) {
    c.x.forEach((x, i) => lines.push(`"${c.label.replace(/"/g, "'")}",${x},${c.y[i]},${c.err && c.err[i] != null ? c.err[i] : ""}`));
  }
  for (const m of plot.markers || []) lines.push(`"${m.label.replace(/"/g, "'")}",${m.x},,`);
  download(`nlpsf-${name}.csv`, "data:text/csv;charset=utf-8," + encodeURIComponent(lines.join("\n") + "\n"));
}

// The plot with its title and a legend a reader can use: a line sample in each series' colour and
// dash, at a size that stays readable when the image is scaled down into a document.
function exportPng(name) {
  const u = state.plots[name];
  const plot = state.exports[name];
  if (!u || !plot) return;
  const source = u.ctx.canvas;
  const scale = Math.max(1, source.width / u.width);
  const font = 14 * scale;
  const row = 20 * scale;
  const titleLines = plot.title.split("\n");
  const entries = [
    ...plot.columns.map((c) => ({ label: c.label, color: c.series.stroke || "#000", dash: c.series.dash, point: !c.series.width })),
    ...(plot.markers || []).map((m) => ({ label: `${m.label}: m = ${fmt(m.x)}`, color: m.color, dash: [6, 4] })),
    ...(plot.shades || []).map((s) => ({ label: s.label, color: s.hatch || s.color, fill: s.color })),
  ];
  const canvas = document.createElement("canvas");
  const ctx = canvas.getContext("2d");
  ctx.font = `${font}px sans-serif`;
  const width = Math.max(...entries.map((e) => ctx.measureText(e.label).width)) + 48 * scale;
  const perRow = Math.max(1, Math.floor((source.width - 16 * scale) / width));
  const top = row * titleLines.length + 10 * scale;
  const bottom = row * Math.ceil(entries.length / perRow) + 12 * scale;
  canvas.width = source.width;
  canvas.height = source.height + top + bottom;
  ctx.fillStyle = "#fff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#1d2330";
  ctx.font = `${font}px sans-serif`;
  titleLines.forEach((line, i) => ctx.fillText(line, 8 * scale, row * (i + 1)));
  ctx.drawImage(source, 0, top);
  entries.forEach((e, i) => {
    const x = 8 * scale + (i % perRow) * width;
    const y = top + source.height + row * (Math.floor(i / perRow) + 1);
    ctx.save();
    if (e.fill) {
      ctx.fillStyle = e.fill;
      ctx.fillRect(x, y - 10 * scale, 28 * scale, 12 * scale);
    } else if (e.point) {
      ctx.fillStyle = e.color;
      ctx.beginPath();
      ctx.arc(x + 14 * scale, y - 4 * scale, 5 * scale, 0, 2 * Math.PI);
      ctx.fill();
    } else {
      ctx.strokeStyle = e.color;
      ctx.lineWidth = 3 * scale;
      ctx.setLineDash((e.dash || []).map((d) => d * scale));
      ctx.beginPath();
      ctx.moveTo(x, y - 4 * scale);
      ctx.lineTo(x + 28 * scale, y - 4 * scale);
      ctx.stroke();
    }
    ctx.restore();
    ctx.fillStyle = "#1d2330";
    ctx.fillText(e.label, x + 36 * scale, y);
  });
  download(`nlpsf-${name}.png`, canvas.toDataURL("image/png"));
}

function download(filename, url) {
  const a = document.createElement("a");
  a.href = url;
  a.download = filename;
  document.body.appendChild(a);
  a.click();
  a.remove();
}

// ---- conditions shared by the calculator and the curves ----------------------------------------

function sharedConditions() {
  const form = document.getElementById("solve-form");
  return {
    sca: form.elements.sca.value,
    exptime: form.elements.exptime.value.trim(),
    beta0: form.elements.beta0.value.trim(),
    full_well: form.elements.full_well.value.trim(),
  };
}

function query(params) {
  const q = new URLSearchParams();
  for (const [k, v] of Object.entries(params)) {
    if (Array.isArray(v)) v.forEach((item) => q.append(k, item));
    else if (v !== null && v !== undefined && v !== "") q.append(k, v);
  }
  return q.toString();
}

// ---- readout: final frame, uniform ramp or an MA table ------------------------------------------

function fillReadout(group) {
  const select = document.getElementById(`${group}-readout`);
  const options = [["final", "final frame (the paper)"], ["uniform", "uniform ramp, N reads"],
    ...(state.meta.ma_tables || []).map((t) => [`table:${t.name}`,
      `MA table ${t.name} (${t.resultants} resultants, ${fmt(t.last_read_s)} s)`])];
  select.innerHTML = options.map(([v, l]) => `<option value="${escapeHtml(v)}">${escapeHtml(l)}</option>`).join("");
  fillSelect(document.getElementById(`${group}-ramp_fit`), state.meta.ramp_fits || ["ols"], "ols",
    (f) => (f === "ols" ? "OLS" : "optimal (read + Poisson)"));
  select.addEventListener("change", () => readoutChanged(group));
}

function readoutChanged(group) {
  const choice = document.getElementById(`${group}-readout`).value;
  document.getElementById(`${group}-ramp`).disabled = choice !== "uniform";
  document.getElementById(`${group}-ramp_fit`).disabled = choice === "final";
  // An MA table's exposure is its last read; leaving a table restores the paper's exposure.
  const exposure = document.getElementById(`${group}-exptime`);
  const durations = (state.meta.ma_tables || []).map((t) => String(t.last_read_s));
  const table = (state.meta.ma_tables || []).find((t) => `table:${t.name}` === choice);
  if (table) exposure.value = String(table.last_read_s);
  else if (durations.includes(exposure.value.trim())) exposure.value = String(state.meta.defaults.solve.exptime);
}

// The request fields of the chosen readout (none for the paper's final frame).
function readoutFields(group) {
  const choice = document.getElementById(`${group}-readout`).value;
  const fit = document.getElementById(`${group}-ramp_fit`).value;
  if (choice === "uniform") return { ramp: numberOrText(document.getElementById(`${group}-ramp`).value), ramp_fit: fit };
  if (choice.startsWith("table:")) return { ma_table: choice.slice(6), ramp_fit: fit };
  return {};
}

// ---- calculator -------------------------------------------------------------------------------

function updateUnknown() {
  const form = document.getElementById("solve-form");
  const unknown = form.elements.solve_for.value;
  for (const name of ["precision", "tolerance", "magnitude"]) {
    const input = form.elements[name];
    input.disabled = name === unknown;
    if (name === unknown) input.value = "";
  }
}

// Reads every number field of a form at once: [values, errors]; `optional` fields may stay empty.
function readNumbers(form, names, optional = []) {
  const values = {};
  const errors = [];
  for (const name of names) {
    const input = form.elements[name];
    if (!input || input.disabled) continue;
    const text = input.value.trim();
    if (text === "") {
      if (!optional.includes(name)) errors.push({ field: name, msg: "enter a value" });
      continue;
    }
    const value = Number(text);
    if (!Number.isFinite(value)) errors.push({ field: name, msg: `"${text.slice(0, 40)}" is not a number` });
    else values[name] = value;
  }
  return [values, errors];
}

async function solve(event) {
  if (event) event.preventDefault();
  const form = document.getElementById("solve-form");
  const errorBox = document.getElementById("solve-error");
  const resultBox = document.getElementById("solve-result");
  clearError(errorBox, form);
  const unknown = form.elements.solve_for.value;
  const shearGiven = ["shear_m", "shear_c"].some((n) => form.elements[n].value.trim() !== "");
  // With a shear budget the tolerance is not a given: the budget and the size ratio take its place.
  const givens = ["precision", "tolerance", "magnitude"].filter((n) => n !== unknown && !(n === "tolerance" && shearGiven));
  const [numbers, errors] = readNumbers(form, ["beta0", "exptime", "full_well", "stars", ...givens, "shear_m", "shear_c", "size_ratio"],
    ["shear_m", "shear_c", "size_ratio"]);
  if (shearGiven && form.elements.size_ratio.value.trim() === "") {
    errors.push({ field: "size_ratio", msg: "a shear budget needs the galaxy-to-PSF size ratio" });
  }
  for (const e of errors) {
    if (givens.includes(e.field) && e.msg === "enter a value") e.msg = "enter a value (give two of precision, tolerance, magnitude)";
  }
  if (errors.length) {
    clearAnswer();
    resultBox.hidden = true;
    const first = errors[0];
    showError(errorBox, form, new ApiError(`${first.field}: ${first.msg}`, first.field, 0, errors));
    return;
  }
  const body = {
    band: form.elements.band.value,
    sca: numberOrText(form.elements.sca.value),
    metric: form.elements.metric.value,
    mode: form.elements.mode.value,
    fidelity: form.elements.fidelity.value,
    ...numbers,
    ...readoutFields("solve"),
  };
  try {
    const s = await api("/solve", { method: "POST", body: JSON.stringify(body), followJob: true });
    form.elements[s.solved_for].value = fmt(s[s.solved_for], 5);
    const names = { precision: "precision p", tolerance: `tolerance T (${METRIC_LABEL[s.metric]})`, magnitude: "magnitude m" };
    const uncertaintyParts = [["statistical", s.uncertainty_statistical], ["fidelity", s.uncertainty_fidelity],
      ["optical model", s.uncertainty_optical_model], ["model", s.uncertainty_model]].filter(([, v]) => v !== null && v !== undefined);
    resultBox.innerHTML = `
      <div class="answer" data-testid="solve-answer">${escapeHtml(names[s.solved_for])} = ${escapeHtml(plusMinus(s[s.solved_for], s.uncertainty))}</div>
      ${s.binding_limit ? `<div class="binding" data-testid="binding-limit">brightest usable star m = ${fmt(s.brightest_usable_magnitude)}:
        ${s.binding_limit === "saturation" ? "saturation binds (the brightest pixel reaches the full well before the NL error reaches T)"
          : "the nonlinearity binds (its error reaches T before the star saturates)"}</div>` : ""}
      ${uncertaintyParts.length ? `<div class="muted">uncertainty: ${uncertaintyParts.map(([k, v]) => `${k} ${fmt(v, 2)}`).join(" · ")}</div>` : ""}
      <div>precision ${fmt(s.precision)} · tolerance ${fmt(s.tolerance)} · magnitude ${fmt(s.magnitude)}
        · slope c(m) = ${fmt(s.slope)} · saturation at m = ${fmt(s.saturation_magnitude)}${s.conditions.ramp
          ? ` (first resultant; a single final frame: m = ${fmt(s.final_frame_saturation_magnitude)})` : ""}</div>
      ${s.shear ? `<div data-testid="shear">${escapeHtml(shearText(s.shear))}</div>` : ""}
      <div class="muted">applies to ${escapeHtml(s.applies_to)}</div>
      ${s.conditions.ramp ? `<div class="muted">slopes from ${escapeHtml(s.conditions.ramp_slopes_from)}</div>` : ""}
      ${s.flags && s.flags.length ? `<ul class="flags">${s.flags.map((f) => `<li>${escapeHtml(f)}</li>`).join("")}</ul>` : ""}
      <p class="conditions">${escapeHtml(conditionsText({ ...s.conditions, band: s.band, sca: s.sca, exptime_s: s.exptime, beta0: s.beta0, fidelity: s.fidelity }))}
        · ${escapeHtml(s.mode)} of ${escapeHtml(METRIC_LABEL[s.metric])}</p>`;
    resultBox.hidden = false;
    state.lastSolution = s;
    await Promise.all([drawRequirementPlot(s), drawCalculatorPlot(s)]);
  } catch (error) {
    resultBox.hidden = true;
    clearAnswer();
    showError(errorBox, form, error);
  }
}

function shearText(shear) {
  const kind = "m" in shear ? "m" : "c";
  const ratio = typeof shear.size_ratio === "number" ? fmt(shear.size_ratio)
    : `${shear.size_ratio.ratios.length} ratios, effective ${fmt(shear.size_ratio.effective)}`;
  if (shear.given === "tolerance") {
    return `implied shear bias |${kind}| = ${plusMinus(shear[kind], shear.uncertainty)} for R_gal/R_psf = ${ratio} (${shear.relation || ""})`;
  }
  return `shear budget |${kind}| = ${fmt(shear[kind])} with R_gal/R_psf = ${ratio} → PSF tolerance T = ${fmt(shear.tolerance)}`;
}

// A failed solve leaves no answer behind: the marker goes from both calculator plots.
function clearAnswer() {
  state.lastSolution = null;
  for (const name of ["req", "calc"]) {
    const plot = state.exports[name];
    const el = document.getElementById(`plot-${name}`);
    delete el.dataset.point;
    el.dataset.answer = "none";
    if (!plot || !plot.columns.some((c) => c.answer)) continue;
    drawPlot(name, { ...plot, columns: plot.columns.filter((c) => !c.answer) });
  }
  document.getElementById("req-readout").textContent = "";
}

// The requirement picture: p(m) = T / (|c(m)| β₀) (× √n in scatter mode) for the tolerance T and a
// few around it; the shipped slopes' statistical and the table level's fidelity uncertainty as bands.
async function drawRequirementPlot(solution) {
  const c = sharedConditions();
  const data = await api(`/curves/slope?${query({ metric: solution.metric, mode: solution.mode, sca: solution.sca,
    exptime: solution.exptime, beta0: solution.beta0, full_well: c.full_well, bands: solution.band })}`);
  const curve = data.curves[0];
  const tolerance = solution.tolerance;
  const averaging = solution.mode === "scatter" ? Math.sqrt(solution.stars || 1) : 1;
  const fid = curve.fidelity_relative_uncertainty;
  const color = BAND_COLORS[curve.band] || "#333";
  const factors = [0.1, 1 / 3, 1, 3, 10];
  const columns = factors.map((f) => {
    const t = tolerance * f;
    const p = curve.slope.map((v) => (v ? (t * averaging) / (Math.abs(v) * solution.beta0) : null));
    // p ∝ 1/|c|: the slope's relative error is p's relative error.
    const err = curve.slope.map((v, i) => (v ? (p[i] * curve.uncertainty[i]) / Math.abs(v) : null));
    const label = `T = ${fmt(t, 3)}${f === 1 ? " (chosen)" : ""}`;
    return { label, x: curve.magnitude, y: p, err, fid, tolerance: t, band: f === 1,
      series: { ...lineSeries(label, color, f === 1 ? undefined : [4, 4]), width: f === 1 ? 3 : 1.2,
        stroke: f === 1 ? color : shade(color, f) } };
  });
  const mSat = solution.final_frame_saturation_magnitude ?? solution.saturation_magnitude;
  // Where 2 β₀ Q_peak ≥ 1 the quadratic is not monotonic; Q_peak = full well at m_sat, × 10^(-0.4 Δm).
  const fullWell = Number(c.full_well) || solution.full_well;
  const mNonlinear = mSat - 2.5 * Math.log10(1 / (2 * solution.beta0 * fullWell));
  const shades = [
    { from: Math.min(...curve.magnitude) - 5, to: mSat, label: `saturated (m < ${fmt(mSat, 3)})`, color: "rgba(120,120,120,0.18)" },
    { from: Math.min(...curve.magnitude) - 5, to: mNonlinear, label: `non-linear: 2β₀Q_peak ≥ 1 (m < ${fmt(mNonlinear, 3)})`,
      color: "rgba(164,22,26,0.08)", hatch: "rgba(164,22,26,0.35)" },
  ];
  columns.push({ label: `answer: m = ${fmt(solution.magnitude)}, p = ${fmt(solution.precision)}`, answer: true, band: false,
    x: [solution.magnitude], y: [solution.precision], series: pointSeries("answer", "#c00000", 12) });
  const ramp = solution.conditions.ramp;
  drawPlot("req", {
    title: `Required ${solution.mode === "bias" ? "Δβ/β₀" : "σβ/β₀"} vs magnitude for ${METRIC_LABEL[solution.metric]} tolerances around T = ${fmt(tolerance)}` +
      `${averaging !== 1 ? ` (averaged over ${solution.stars} stars)` : ""}${ramp ? " (final-frame slopes)" : ""}\n${conditionsText(curve.conditions)}`,
    xLabel: "magnitude (AB)",
    yLabel: `precision p = ${solution.mode === "bias" ? "Δβ/β₀" : "σβ/β₀"}`,
    logY: true,
    columns,
    shades,
    cursorAt: solution.magnitude,
  });
  const el = document.getElementById("plot-req");
  el.dataset.point = `${solution.magnitude},${solution.precision}`;
  el.dataset.answer = "shown";
  const u = state.plots.req;
  if (!u) return;
  const readout = document.getElementById("req-readout");
  const show = (i) => {
    if (i == null) i = u.defaultIdx;
    const m = u.data[0][i];
    const chosen = columns[2];
    const j = chosen.x.indexOf(m);
    if (j < 0 || chosen.y[j] == null) return;
    const p = chosen.y[j];
    const stat = chosen.err[j];
    const fidelity = fid != null ? p * fid : null;
    const where = m < mNonlinear ? " — non-linear regime" : m < mSat ? " — saturated" : "";
    readout.textContent = `m = ${fmt(m, 4)}: p ≤ ${fmt(p, 3)} (± ${fmt(stat, 2)} stat` +
      `${fidelity != null ? `, ± ${fmt(fidelity, 2)} fidelity` : ""}) keeps ${METRIC_LABEL[solution.metric]} within T = ${fmt(tolerance, 3)}${where}`;
    readout.dataset.magnitude = String(m);
    readout.dataset.precision = String(p);
  };
  u.hooks.setCursor = [(plot) => show(plot.cursor.idx)];
  show(null);
}

// Lighter (tolerance < T) or darker (> T) versions of the band colour for the neighbouring curves.
function shade(hex, factor) {
  const n = parseInt(hex.slice(1), 16);
  const mix = factor < 1 ? 255 : 0;
  const w = Math.min(0.6, 0.25 * Math.abs(Math.log10(factor)) + 0.2);
  const channel = (shift) => Math.round(((n >> shift) & 255) * (1 - w) + mix * w);
  return `rgb(${channel(16)},${channel(8)},${channel(0)})`;
}

async function drawCalculatorPlot(solution) {
  const c = sharedConditions();
  const data = await api(`/curves/slope?${query({ metric: solution.metric, mode: solution.mode, sca: solution.sca,
    exptime: solution.exptime, beta0: solution.beta0, full_well: c.full_well, bands: solution.band })}`);
  const curve = data.curves[0];
  const signed = curve.slope.some((v) => v < 0);
  const abs = (v) => (v === null ? null : Math.abs(v));
  const ramp = solution.conditions.ramp;
  const label = `${curve.band} ${solution.mode} slope${ramp ? ", final frame" : ""}${signed ? " (|c|)" : ""}`;
  const columns = [
    { label, x: curve.magnitude, y: curve.slope.map(abs), err: curve.uncertainty, fid: curve.fidelity_relative_uncertainty,
      series: lineSeries(label, BAND_COLORS[curve.band] || "#333") },
  ];
  const markers = [{ x: solution.final_frame_saturation_magnitude ?? solution.saturation_magnitude,
    label: "saturation, final frame", color: "#555" }];
  if (ramp) {
    markers.push({ x: solution.saturation_magnitude, label: "saturation, ramp (first resultant)", color: "#c00000" });
    const factor = ramp.quadratic_beta_factor;
    const exactFrom = solution.conditions.ramp_table_exact_from_magnitude;
    if (factor) {
      // OLS: the ramp is the final frame at beta_eff = c beta0 wherever no pixel drops a resultant.
      const mapped = await api(`/curves/slope?${query({ metric: solution.metric, mode: solution.mode, sca: solution.sca,
        exptime: solution.exptime, beta0: solution.beta0 * factor, full_well: c.full_well, bands: solution.band })}`);
      const rampCurve = mapped.curves[0];
      const keep = rampCurve.magnitude.map((m) => exactFrom === null || m >= exactFrom);
      const rampLabel = `ramp ${ramp.ma_table} (tables at β_eff = ${fmt(factor)} β₀)`;
      columns.push({ label: rampLabel, x: rampCurve.magnitude.filter((_, i) => keep[i]),
        y: rampCurve.slope.filter((_, i) => keep[i]).map((v) => abs(v * factor)),
        err: rampCurve.uncertainty.filter((_, i) => keep[i]).map((e) => e * factor),
        series: lineSeries(rampLabel, "#c00000", [6, 3]) });
    }
  }
  columns.push({ label: `answer: m = ${fmt(solution.magnitude)}, c = ${fmt(solution.slope)}`, x: [solution.magnitude],
    y: [abs(solution.slope)], answer: true, band: false, series: pointSeries("answer", "#c00000", 12) });
  drawPlot("calc", {
    markers,
    cursorAt: solution.magnitude,
    title: `${label} vs magnitude; answer marked${ramp ? `; up the ramp: ${ramp.description}` : ""}\n${conditionsText(curve.conditions)}`,
    xLabel: "magnitude (AB)",
    yLabel: `${solution.mode === "bias" ? "d" : "σ"}(${METRIC_LABEL[solution.metric]})/${solution.mode === "bias" ? "dβ" : "σβ"} [e⁻]`,
    logY: true,
    columns,
  });
  document.getElementById("plot-calc").dataset.point = `${solution.magnitude},${solution.slope}`;
  document.getElementById("plot-calc").dataset.answer = "shown";
}

// ---- curves -----------------------------------------------------------------------------------

function paperOn() {
  return document.getElementById("paper-overlay").checked && state.paper;
}

async function drawSlopes() {
  const c = sharedConditions();
  const metric = document.getElementById("slopes-metric").value;
  const mode = document.getElementById("slopes-mode").value;
  const data = await api(`/curves/slope?${query({ metric, mode, ...c })}`);
  const signed = data.curves.some((curve) => curve.slope.some((v) => v < 0));
  const columns = data.curves.map((curve) => ({
    label: curve.band,
    x: curve.magnitude,
    y: curve.slope.map((v) => Math.abs(v)),
    err: curve.uncertainty,
    fid: curve.fidelity_relative_uncertainty,
    series: lineSeries(curve.band, BAND_COLORS[curve.band] || "#333"),
  }));
  const paper = paperOn();
  if (paper && metric !== "e") {
    const figure = mode === "bias" ? paper.fig3_bias_slopes_per_beta : paper.fig5_scatter_slopes_per_sigma_beta;
    for (const [band, values] of Object.entries(figure)) {
      columns.push({ label: `${band} (paper)`, x: paper.magnitudes, y: values[metric].map((v) => Math.abs(v)),
        series: pointSeries(`${band} (paper)`, BAND_COLORS[band] || "#333", 7) });
    }
  }
  const first = data.curves[0];
  const title = `${mode} slope of ${METRIC_LABEL[metric]} vs magnitude${signed ? " (absolute values: the slope changes sign)" : ""}\n` +
    conditionsText({ ...first.conditions, band: "all bands" });
  document.getElementById("slopes-caption").textContent =
    `${data.source}. ${title.split("\n")[1]}. Lines: this tool's tables; points: the paper (Cycle-5 optics), when shown.` +
    (paper && metric === "e" ? " The paper has no |Δe| data." : "");
  drawPlot("slopes", {
    title,
    xLabel: "magnitude (AB)",
    yLabel: `${mode === "bias" ? "d" : "σ"}(${METRIC_LABEL[metric]})/${mode === "bias" ? "dβ" : "σβ"} [e⁻]`,
    logY: true,
    columns,
  });
}

// Fresh simulation points for the beta or the sigma_beta plot: one series per (β, σβ) group so that
// several simulations at different β are all drawn, each named by its β.
function simulationPoints(kind, band, metric, magnitude) {
  const sim = state.lastSimulation;
  if (!sim || metric === "e") return [];
  const key = METRIC_KEY[metric];
  const rows = sim.results.filter((r) => r.band === band && Math.abs(r.magnitude - magnitude) < 1e-9 &&
    (kind === "beta" ? r.sigma_beta === 0 : r.sigma_beta > 0));
  if (rows.length === 0) return [];
  // The standard error of a mean; for a spread over n draws, std / sqrt(2(n - 1)).
  const point = (r) => (kind === "beta"
    ? [r.beta, r[key].mean, r[key].stderr]
    : [r.sigma_beta, r[key].std, r[key].std / Math.sqrt(2 * Math.max(r.realizations - 1, 1))]);
  const groups = new Map();
  for (const r of rows) {
    const group = kind === "beta" ? `σβ = ${fmt(r.sigma_beta)}` : `β = ${fmt(r.beta)}`;
    if (!groups.has(group)) groups.set(group, []);
    groups.get(group).push(point(r));
  }
  const several = groups.size > 1;
  return [...groups.entries()].map(([group, points], k) => {
    const label = `fresh simulation${kind === "sigma" || several ? `, ${group}` : ""} (${sim.fidelity}, ${rows[0].realizations} realizations)`;
    return { label, x: points.map((p) => p[0]), y: points.map((p) => p[1]), err: points.map((p) => p[2]), band: false,
      series: pointSeries(label, SERIES_COLORS[k % SERIES_COLORS.length], 9) };
  });
}

// Says which fresh simulation points are drawn, and which are not (another band, magnitude or |Δe|).
function freshNote(drawn, band, magnitude, metric) {
  const sim = state.lastSimulation;
  if (!sim) return "";
  const shown = drawn.reduce((n, c) => n + c.x.length, 0);
  const others = sim.results.filter((r) => r.sigma_beta > 0).length - shown;
  const parts = [` Points: ${shown ? `each β of the last fresh simulation at ${band}, m = ${fmt(magnitude)} (${drawn.length} series)` : "none at these settings"}`];
  if (others > 0) parts.push(`${others} more at other bands or magnitudes (choose them above, or see the table)`);
  if (metric === "e") parts.push("simulations give e₁ and e₂, not |Δe|");
  return parts.join("; ") + ".";
}

async function drawBeta() {
  const c = sharedConditions();
  const band = document.getElementById("beta-band").value;
  const metric = document.getElementById("beta-metric").value;
  const magnitude = document.getElementById("beta-magnitude").value.trim();
  const log = document.getElementById("beta-log").checked;
  const data = await api(`/curves/beta?${query({ band, metric, magnitude, ...c })}`);
  const label = `${band}, m = ${fmt(data.magnitude)} (table, first order)`;
  const columns = [{ label, x: data.beta, y: data.values, err: data.uncertainty, fid: data.fidelity_relative_uncertainty,
    series: lineSeries(label, BAND_COLORS[band] || "#333") }];
  const paper = paperOn();
  if (paper && metric !== "e" && paper["fig2_at_m18.3"][band]) {
    const fig = paper["fig2_at_m18.3"][band];
    columns.push({ label: `${band} paper, m = 18.3`, x: fig.beta, y: fig[METRIC_KEY[metric]],
      series: pointSeries(`${band} paper, m = 18.3`, "#555", 7) });
  }
  columns.push(...simulationPoints("beta", band, metric, Number(magnitude)));
  if (log) {
    // Δe1 and Δe2 can be negative: a log axis shows their size.
    for (const column of columns) column.y = column.y.map((v) => (v === null ? null : Math.abs(v)));
  }
  const title = `${METRIC_LABEL[metric]} vs β at m = ${fmt(data.magnitude)}\n${conditionsText(data.conditions)}`;
  document.getElementById("beta-caption").textContent = `${data.source}. ${conditionsText(data.conditions)}. ` +
    `Slope c = ${fmt(data.slope)} per unit β (relative uncertainty: statistical ${fmt(data.uncertainty.at(-1) / Math.abs(data.values.at(-1)), 2)}` +
    `${data.fidelity_relative_uncertainty != null ? `, fidelity ${fmt(data.fidelity_relative_uncertainty, 2)}` : ""}).` +
    (data.flags.length ? ` Flags: ${data.flags.join("; ")}` : "");
  const yLabel = log ? `|${METRIC_LABEL[metric]}|` : METRIC_LABEL[metric];
  drawPlot("beta", { title, xLabel: "β [1/e⁻]", yLabel, columns, logX: log, logY: log });
}

async function drawSigma() {
  const c = sharedConditions();
  const band = document.getElementById("sigma-band").value;
  const metric = document.getElementById("sigma-metric").value;
  const magnitude = document.getElementById("sigma-magnitude").value.trim();
  const log = document.getElementById("sigma-log").checked;
  const data = await api(`/curves/sigma_beta?${query({ band, metric, magnitude, ...c })}`);
  const label = `${band}, m = ${fmt(data.magnitude)} (table, first order)`;
  const columns = [{ label, x: data.sigma_beta, y: data.values, err: data.uncertainty, fid: data.fidelity_relative_uncertainty,
    series: lineSeries(label, BAND_COLORS[band] || "#333") }];
  const fresh = simulationPoints("sigma", band, metric, Number(magnitude));
  columns.push(...fresh);
  const title = `σ(${METRIC_LABEL[metric]}) vs σβ at m = ${fmt(data.magnitude)}\n${conditionsText(data.conditions)}`;
  document.getElementById("sigma-caption").textContent = `${data.source}. ${conditionsText(data.conditions)}. ` +
    `Scatter slope = ${fmt(data.slope)} per unit σβ.` + (data.flags.length ? ` Flags: ${data.flags.join("; ")}` : "") +
    freshNote(fresh, band, Number(magnitude), metric);
  drawPlot("sigma", { title, xLabel: "σβ [1/e⁻]", yLabel: `σ(${METRIC_LABEL[metric]})`, columns, logX: log, logY: log });
}

async function drawCurves() {
  const box = document.getElementById("curves-error");
  clearError(box, null);
  const results = await Promise.allSettled([drawSlopes(), drawBeta(), drawSigma()]);
  const failed = results.find((r) => r.status === "rejected");
  if (failed) showError(box, null, failed.reason);
}

// ---- simulations --------------------------------------------------------------------------------

async function runSimulation(event) {
  event.preventDefault();
  const form = document.getElementById("sim-form");
  const errorBox = document.getElementById("sim-error");
  clearError(errorBox, form);
  const body = {
    band: form.elements.band.value,
    sca: numberOrText(form.elements.sca.value),
    magnitudes: listOf(form.elements.magnitudes.value),
    betas: listOf(form.elements.betas.value),
    sigma_betas: listOf(form.elements.sigma_betas.value),
    exptime: numberOrText(form.elements.exptime.value),
    fidelity: form.elements.fidelity.value,
    realizations: numberOrText(form.elements.realizations.value),
    seed: numberOrText(form.elements.seed.value),
    oversampling: numberOrText(form.elements.oversampling.value),
    stamp: numberOrText(form.elements.stamp.value),
    ...readoutFields("sim"),
  };
  if (document.getElementById("scene-use").checked) {
    const scene = sceneBody();
    if (scene) body.scene = scene;
  }
  setProgress(0, "submitting");
  try {
    const job = await api("/simulations", { method: "POST", body: JSON.stringify(body) });
    followJob(job);
  } catch (error) {
    setProgress(0, "not started");
    showError(errorBox, form, error);
  }
}

// ---- scene and impact ------------------------------------------------------------------------

function sceneBody() {
  const f = document.getElementById("scene-form").elements;
  const scene = {};
  const text = (name) => f[name].value.trim();
  const given = (name) => text(name) !== "" && text(name).toLowerCase() !== "none";
  if (f.preset.value) scene.preset = f.preset.value;
  if (given("position")) scene.position = listOf(text("position"));
  if (given("sed")) scene.sed = text("sed");
  for (const name of ["jitter", "charge_diffusion", "bfe", "background"]) {
    if (given(name)) scene[name] = numberOrText(text(name));
  }
  if (given("ipc")) scene.ipc = numberOrText(text("ipc"));
  if (f.ipc_order.value) scene.ipc_order = f.ipc_order.value;
  if (given("nl_coefficients")) scene.nl_coefficients = listOf(text("nl_coefficients"));
  return Object.keys(scene).length ? scene : null;
}

// The service names scene fields "scene.jitter"; the form's inputs are named "jitter".
function sceneError(error) {
  const field = error.field && error.field.startsWith("scene.") ? error.field.slice(6) : error.field;
  return new ApiError(error.message, field, error.status);
}

async function measureImpact(event) {
  if (event) event.preventDefault();
  const form = document.getElementById("scene-form");
  const box = document.getElementById("scene-error");
  const button = document.getElementById("impact-button");
  clearError(box, form);
  const s = document.getElementById("solve-form").elements;
  const body = {
    band: s.band.value,
    sca: numberOrText(s.sca.value),
    metric: s.metric.value,
    mode: s.mode.value,
    beta0: numberOrText(s.beta0.value),
    exptime: numberOrText(s.exptime.value),
    magnitude: numberOrText(s.magnitude.value) ?? 18.3,
    realizations: 30,
  };
  const scene = sceneBody();
  if (scene) body.scene = scene;
  button.disabled = true;
  button.textContent = "Measuring…";
  try {
    showImpact(await api("/impact", { method: "POST", body: JSON.stringify(body), followJob: true }));
  } catch (error) {
    showError(box, form, sceneError(error));
  } finally {
    button.disabled = false;
    button.textContent = "Measure impact";
  }
}

function showImpact(report) {
  const c = report.conditions;
  const metric = c.metric;
  const values = report.effects.map((e) => e.impact[metric]);
  const largest = Math.max(1e-12, ...values.filter((v) => v !== null).map(Math.abs));
  document.getElementById("impact-conditions").textContent =
    `${c.band} · SCA ${c.sca} · m = ${fmt(c.magnitude)} · β₀ = ${fmt(c.beta0)} /e⁻ · ${METRIC_LABEL[metric] || metric} ${c.mode} slope · ` +
    `scene: ${c.scene_description} · impact = slope with ÷ without − 1 (linear response, ${c.realizations} centroids)`;
  document.getElementById("impact-bars").innerHTML = report.effects
    .map((e, k) => {
      const v = values[k];
      const width = v === null ? 0 : (50 * Math.abs(v)) / largest;
      const side = v !== null && v < 0 ? "neg" : "pos";
      const label = v === null ? "n/a" : `${v > 0 ? "+" : ""}${fmt(100 * v, 3)} %`;
      return `<div class="bar-row" data-effect="${escapeHtml(e.name)}" title="${escapeHtml(e.note || "")}">` +
        `<span class="bar-name">${escapeHtml(e.name)}${e.on ? " (on)" : ""}</span>` +
        `<span class="bar-track"><span class="bar ${side}" style="width:${width}%"></span></span>` +
        `<span class="bar-value">${label}</span></div>`;
    })
    .join("");
  document.getElementById("impact-result").hidden = false;
}

function setProgress(fraction, message) {
  document.getElementById("sim-progress").value = fraction;
  document.getElementById("sim-progress-text").textContent = `${Math.round(fraction * 100)}% — ${message}`;
}

function followJob(job) {
  const cancel = document.getElementById("sim-cancel");
  const submit = document.getElementById("sim-button");
  if (state.polling) clearTimeout(state.polling);
  const step = async (current) => {
    setProgress(current.progress, current.cached ? "answered from stored results" : current.message);
    if (["queued", "running"].includes(current.status)) {
      cancel.disabled = false;
      submit.disabled = true;
      cancel.onclick = async () => {
        try {
          step(await api(`/simulations/${current.id}`, { method: "DELETE" }));
        } catch (error) {
          showError(document.getElementById("sim-error"), null, error);
        }
      };
      state.polling = setTimeout(async () => {
        try {
          step(await api(`/simulations/${current.id}`));
        } catch (error) {
          showError(document.getElementById("sim-error"), null, error);
          cancel.disabled = true;
          submit.disabled = false;
        }
      }, 250);
      return;
    }
    cancel.disabled = true;
    submit.disabled = false;
    if (current.status === "done") {
      setProgress(1, current.cached ? "done (answered from stored results)" : "done");
      showSimulation(current.result);
    } else {
      const reason = current.error && current.error.message ? `: ${current.error.message}` : "";
      showError(document.getElementById("sim-error"), null, new ApiError(`simulation ${current.status} — ${current.message}${reason}`));
    }
  };
  step(job);
}

function showSimulation(result) {
  state.lastSimulation = result;
  const box = document.getElementById("sim-result");
  document.getElementById("sim-conditions").textContent = `${result.source}. ${conditionsText(result.conditions)}`;
  const head = ["m", "β", "σβ", "flux [e⁻]", "peak [e⁻]", "ΔR/R", "Δe₁", "Δe₂", "σ(ΔR/R)", "flags"];
  const table = document.getElementById("sim-table");
  table.tHead.innerHTML = `<tr>${head.map((h) => `<th>${escapeHtml(h)}</th>`).join("")}</tr>`;
  table.tBodies[0].innerHTML = result.results.map((r) => `<tr>
      <td>${fmt(r.magnitude)}</td><td>${fmt(r.beta)}</td><td>${fmt(r.sigma_beta)}</td>
      <td>${fmt(r.flux_electrons)}</td><td>${fmt(r.peak_electrons)}</td>
      <td>${plusMinus(r.dR_over_R.mean, r.dR_over_R.stderr)}</td><td>${plusMinus(r.de1.mean, r.de1.stderr)}</td>
      <td>${plusMinus(r.de2.mean, r.de2.stderr)}</td><td>${fmt(r.dR_over_R.std)}</td>
      <td class="flags-cell">${escapeHtml(r.flags.join("; "))}</td></tr>`).join("");
  box.hidden = false;
  const first = result.results[0];
  for (const prefix of ["beta", "sigma"]) {
    document.getElementById(`${prefix}-band`).value = first.band;
    document.getElementById(`${prefix}-magnitude`).value = String(first.magnitude);
  }
  drawCurves();
}

function simulationCsv() {
  const result = state.lastSimulation;
  if (!result) return;
  const c = result.conditions;
  const lines = [`# ${result.source}; ${conditionsText(c)}`,
    "band,sca,magnitude,beta,beta_convention,sigma_beta,realizations,flux_electrons,peak_electrons," +
    "dR_over_R_mean,dR_over_R_std,dR_over_R_stderr,de1_mean,de1_std,de1_stderr,de2_mean,de2_std,de2_stderr,flags"];
  for (const r of result.results) {
    lines.push([r.band, r.sca, r.magnitude, r.beta, r.beta_convention, r.sigma_beta, r.realizations, r.flux_electrons, r.peak_electrons,
      r.dR_over_R.mean, r.dR_over_R.std, r.dR_over_R.stderr, r.de1.mean, r.de1.std, r.de1.stderr, r.de2.mean, r.de2.std, r.de2.stderr,
      `"${r.flags.join("; ").replace(/"/g, "'")}"`].join(","));
  }
  download("nlpsf-simulation.csv", "data:text/csv;charset=utf-8," + encodeURIComponent(lines.join("\n") + "\n"));
}

// ---- start ------------------------------------------------------------------------------------

async function init() {
  const meta = await api("/meta");
  state.meta = meta;
  const d = meta.defaults.solve;
  const bands = meta.table_bands && meta.table_bands.length ? meta.table_bands : meta.bands;
  document.getElementById("versions").textContent = `code ${meta.code_version} · optical data: ${meta.data_version}`;
  const settings = (meta.tables && meta.tables.settings) || {};
  document.getElementById("table-version").textContent =
    Object.entries(settings).map(([k, v]) => `${k} ${v}`).join(" · ") + (meta.tables ? ` · fingerprint ${meta.tables.fingerprint}` : "");
  fillSelect(document.getElementById("solve-band"), bands, "H158");
  fillSelect(document.getElementById("solve-sca"), meta.scas, d.sca);
  for (const id of ["solve-metric", "slopes-metric", "beta-metric", "sigma-metric"]) {
    fillSelect(document.getElementById(id), meta.metrics, d.metric, (m) => `${m} (${METRIC_LABEL[m] || m})`);
  }
  fillSelect(document.getElementById("solve-mode"), meta.modes, d.mode);
  fillSelect(document.getElementById("slopes-mode"), meta.modes, d.mode);
  fillSelect(document.getElementById("solve-fidelity"), meta.fidelities, d.fidelity || "table");
  for (const id of ["beta-band", "sigma-band", "sim-band"]) fillSelect(document.getElementById(id), bands, "H158");
  fillSelect(document.getElementById("sim-sca"), meta.scas, 18);
  fillSelect(document.getElementById("sim-fidelity"), meta.simulation_fidelities, "monte_carlo");
  fillReadout("solve");
  fillReadout("sim");

  document.getElementById("solve-form").addEventListener("submit", solve);
  document.querySelectorAll('input[name="solve_for"]').forEach((r) => r.addEventListener("change", updateUnknown));
  updateUnknown();
  document.getElementById("sim-form").addEventListener("submit", runSimulation);
  document.getElementById("sim-csv").addEventListener("click", simulationCsv);
  document.getElementById("scene-form").addEventListener("submit", measureImpact);
  document.querySelectorAll("[data-png]").forEach((b) => b.addEventListener("click", () => exportPng(b.dataset.png)));
  document.querySelectorAll("[data-csv]").forEach((b) => b.addEventListener("click", () => exportCsv(b.dataset.csv)));
  const redraw = () => drawCurves();
  for (const id of ["slopes-metric", "slopes-mode", "beta-band", "beta-metric", "beta-log", "sigma-band", "sigma-metric", "sigma-log"]) {
    document.getElementById(id).addEventListener("change", redraw);
  }
  for (const id of ["beta-magnitude", "sigma-magnitude", "solve-sca", "solve-exptime", "solve-beta0", "solve-full_well"]) {
    document.getElementById(id).addEventListener("change", redraw);
  }
  document.getElementById("paper-overlay").addEventListener("change", async () => {
    if (!state.paper) state.paper = await api("/paper");
    drawCurves();
  });
  let resizeTimer = null;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => {
      for (const [name, u] of Object.entries(state.plots)) {
        const el = document.getElementById(`plot-${name}`);
        u.setSize({ width: Math.max(320, el.clientWidth), height: 320 });
      }
    }, 150);
  });
  await Promise.allSettled([solve(null), drawCurves()]);
  document.body.dataset.ready = "true";
}

document.addEventListener("DOMContentLoaded", () => {
  init().catch((error) => {
    const box = document.getElementById("solve-error");
    showError(box, null, new ApiError(`the page could not load its data: ${error.message}`));
    document.body.dataset.ready = "error";
  });
});

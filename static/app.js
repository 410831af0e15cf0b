// The nlpsf page: calculator, curves, fresh simulations, impact and batch over the REST API (/api/v1).
// Plain JavaScript and the vendored uPlot; no build step, no network beyond this server.
// The page draws and formats: every number it draws comes from the API (api/v1/page/* for the plots).
"use strict";

const API = "api/v1";
// Okabe & Ito's colour-blind-safe palette, and a dash pattern per band so that no two bands rely on hue.
const BAND_COLORS = {
  R062: "#E69F00", Z087: "#56B4E9", Y106: "#0072B2", J129: "#009E73",
  H158: "#D55E00", F184: "#CC79A7", W146: "#000000", K213: "#8C6D00",
};
const BAND_DASH = {
  R062: [3, 3, 8, 3], Z087: [10, 4], Y106: [2, 3], J129: [12, 3, 2, 3], H158: [], F184: [6, 6], W146: [1, 2], K213: [14, 4, 2, 4, 2, 4],
};
const SERIES_COLORS = ["#c00000", "#0072B2", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000", "#8C6D00"];
const METRIC_LABEL = { size: "ΔR/R", e1: "Δe₁", e2: "Δe₂", e: "|Δe|" };
const METRIC_NAME = { size: "size ΔR/R", e1: "ellipticity Δe₁", e2: "ellipticity Δe₂", e: "ellipticity |Δe|" };
const METRIC_KEY = { size: "dR_over_R", e1: "de1", e2: "de2" };
const MODE_NAME = { bias: "bias (mean β off)", scatter: "scatter (pixel to pixel)" };
// Plain names for every request field the server may name in a refusal.
const FIELD_NAMES = {
  band: "band", sca: "detector (SCA)", metric: "PSF quantity", mode: "kind of error", beta0: "nonlinearity β₀",
  exptime: "exposure", full_well: "full well", fidelity: "method", accuracy: "accuracy", ma_table: "readout",
  ramp: "number of reads", ramp_fit: "ramp fit", read_noise: "read noise", stars: "stars averaged",
  shear_m: "shear budget |m|", shear_c: "shear budget |c|", size_ratio: "galaxy-to-PSF size ratio",
  precision: "precision", tolerance: "tolerance", magnitude: "magnitude", magnitudes: "magnitudes", betas: "β values",
  sigma_betas: "σβ values", realizations: "realizations", seed: "seed", oversampling: "oversampling", stamp: "stamp size",
  position: "position on the detector", sed: "star colour (SED)", jitter: "pointing jitter",
  charge_diffusion: "charge diffusion", ipc: "interpixel capacitance", ipc_order: "interpixel capacitance order",
  nl_coefficients: "NL beyond the quadratic", bfe: "brighter-fatter coefficient", background: "sky background",
  scene: "scene", csv: "CSV", over_field: "over the field", throughput: "throughput",
};
// The page's words for each scene effect, by the registry's name (GET /api/v1/meta → scene_effects,
// nlpsf.sim.scene.REGISTRY, is the list of effects and their facts); an effect without words here shows
// under its registry name.
const EFFECT_WORDS = {
  position: ["position on the detector", "the optics change across a detector: the PSF at a corner differs from the centre the tables hold"],
  sed: ["star colour (SED)", "a real star spans the band's wavelengths; the tables use one wavelength"],
  jitter: ["pointing jitter", "the telescope's pointing wanders during the exposure and blurs the PSF"],
  charge_diffusion: ["charge diffusion", "charge spreads to neighbouring pixels before it is collected"],
  ipc: ["interpixel capacitance", "a pixel's signal leaks capacitively into its neighbours (a few per cent for Roman's detectors)"],
  nl_polynomial: ["NL beyond the quadratic", "the detector's response has cubic and higher terms besides S = Q − βQ²"],
  brighter_fatter: ["brighter-fatter effect", "collected charge repels new charge, so bright stars look bigger"],
  background: ["sky background", "sky and dark current add charge under the star and move it up the nonlinear curve"],
};
// Not a scene effect, but explained beside them (the optical model's own uncertainty).
const PUPIL_SCALE_WORDS = ["pupil-mask scale rule", "two readings of how the pupil mask is scaled; the difference measures the optical model's own uncertainty"];

function effectWords(name) {
  return EFFECT_WORDS[name] || [String(name).replace(/_/g, " "), ""];
}

// One registry entry in words: the page's wording, then the registry's facts.
function effectExplanation(effect) {
  const [name, about] = effectWords(effect.name);
  const where = effect.kind === "optical" ? "optical: acts on the PSF before the pixels" : "detector: acts in the pixels";
  const values = Object.entries(effect.nominal || {}).filter(([, v]) => typeof v === "number").map(([k, v]) => `${k} = ${fmt(v)}`);
  return [name, `${about ? `${about}. ` : ""}${where}; the value tried when a scene leaves it off: ` +
    `${values.length ? `${values.join(", ")}, ` : ""}${plainNote(effect.source)}; combines with ${effect.combines_with}`];
}

// Up the ramp a star is usable until its brightest pixel saturates in the resultant a slope needs
// (usually the second: one resultant gives no slope; docs/ramps.md), named by the ramp's conditions.
function limitResultantText(ramp) {
  const k = ramp && ramp.limit_resultant;
  if (!k) return "the resultant a slope needs";
  const ordinal = ["first", "second", "third"][k - 1] || `${k}th`;
  const end = ramp.limit_resultant_end_s;
  return `its ${ordinal} resultant, the one a slope needs${end ? `, ends at ${fmt(end, 4)} s` : ""}`;
}

// Each flag on an answer: its message and, from the code catalogue (GET /api/v1/meta → flag_codes),
// what it means, in a disclosure that opens by keyboard (Enter/Space on its summary).
function flagsList(flags, codes) {
  const catalogue = new Map(((state.meta && state.meta.flag_codes) || []).map((c) => [c.code, c.meaning]));
  const items = flags.map((message, k) => {
    const meaning = codes && catalogue.get(codes[k]);
    const about = meaning
      ? `<details class="flag-about"><summary>what this means</summary><span data-flag-code="${escapeHtml(codes[k])}">${escapeHtml(meaning)}</span></details>`
      : "";
    return `<li>${escapeHtml(plainWords(message))}${about}</li>`;
  });
  return `<ul class="flags" data-testid="answer-flags">${items.join("")}</ul>`;
}

const FIDELITIES = {
  table: ["tables", "the shipped slope tables, interpolated: instant; the uncertainty includes their measured error"],
  linear: ["linear response", "a fresh simulation of the first-order response to β: seconds"],
  monte_carlo: ["Monte Carlo", "a fresh simulation with random centroids and the full nonlinearity: slower, the reference"],
  monte_carlo_polychromatic: ["Monte Carlo, all wavelengths", "Monte Carlo over the band's wavelengths: the slowest"],
};
const PAPER_SCENE = "the paper's scene (detector centre, one wavelength, quadratic NL only)";

const state = {
  meta: null, paper: null, presets: null, plots: {}, exports: {}, lastSimulation: null, polling: null,
  lastSolution: null, lastRequest: null, pinned: [], batch: null, kbIdx: {},
};

class ApiError extends Error {
  // errors: [{field, msg}] -- every bad field the server (or the page's own check) found.
  constructor(message, field, status, errors = [], extra = {}) {
    super(message);
    this.field = field;
    this.status = status;
    this.errors = errors;
    Object.assign(this, extra);
  }
}

// ---- the connection: an unreachable server is named and retried -------------------------------

const connection = {
  down: false,
  attempt: 0,
  timer: null,
  retries: new Map(),
  // Remember what to do again once the server answers (one action per key, the latest wins).
  lost(key, retry) {
    if (key && retry) this.retries.set(key, retry);
    if (this.down) return;
    this.down = true;
    this.attempt = 0;
    this.poll();
  },
  show(text, kind) {
    const box = document.getElementById("connection");
    box.textContent = text;
    box.dataset.state = kind;
    box.hidden = !text;
  },
  async poll() {
    this.attempt += 1;
    const where = new URL(".", location.href).href;
    this.show(`The nlpsf server at ${where} cannot be reached. Retrying every 3 s (attempt ${this.attempt}); ` +
      "what you asked for is redone when it answers.", "down");
    try {
      const response = await fetch(`${API}/health`, { cache: "no-store" });
      if (response.ok) return this.back();
    } catch (_) {
      // still down
    }
    this.timer = setTimeout(() => this.poll(), 3000);
  },
  back() {
    this.down = false;
    this.show("Connected to the server again.", "up");
    setTimeout(() => { if (!this.down) this.show("", "up"); }, 4000);
    const pending = [...this.retries.values()];
    this.retries.clear();
    pending.forEach((retry) => retry());
  },
};

async function api(path, options = {}) {
  const { followJob: follow = false, raw = false, onJob = null, onProgress = null, ...fetchOptions } = options;
  let response;
  try {
    response = await fetch(`${API}${path}`, {
      ...fetchOptions,
      headers: { "Content-Type": "application/json", ...(fetchOptions.headers || {}) },
    });
  } catch (_) {
    throw unreachable();
  }
  if (raw && response.ok) return response.text();
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
    const location = response.headers.get("Location") || `${API}/simulations/${body.id}`;
    if (onJob) onJob(location);
    return waitForJob(location, onProgress);
  }
  return body;
}

function unreachable() {
  return new ApiError(`the nlpsf server at ${new URL(".", location.href).href} cannot be reached`, null, 0, [], { unreachable: true });
}

// Follows a job to its end; a lost connection waits for the server and asks again (the job's record
// in the server's store says how it really ended, even across a restart).
async function waitForJob(location, onProgress = null) {
  for (;;) {
    await new Promise((resolve) => setTimeout(resolve, 500));
    let response;
    try {
      response = await fetch(location, { cache: "no-store" });
    } catch (_) {
      await new Promise((resolve) => connection.lost(`wait:${location}`, resolve));
      continue;
    }
    const job = await response.json().catch(() => null);
    if (!response.ok || !job) {
      throw new ApiError((job && job.detail) || `the server answered ${response.status}`, null, response.status, []);
    }
    if (onProgress) onProgress(job);
    if (job.status === "done") return job.result;
    if (["failed", "cancelled", "interrupted"].includes(job.status)) {
      const error = job.error || {};
      throw new ApiError(jobEnding(job), error.field || null, 500, [], { jobStatus: job.status });
    }
  }
}

// "40 % · about 12 s left": the fraction the server reports and the time its own clock says is left.
// `since` (ms, this page's clock): when the page asked; else the server's own start and last update.
function progressText(job, since = null) {
  const fraction = Math.max(0, Math.min(1, job.progress || 0));
  const parts = [`${Math.round(100 * fraction)} % done`];
  if (job.status === "queued") return `queued${job.queue_position ? ` (${job.queue_position} ahead)` : ""}`;
  const elapsed = since !== null ? (Date.now() - since) / 1000 : job.started_at && job.updated_at ? job.updated_at - job.started_at : null;
  const seconds = (t) => (t < 90 ? `${Math.round(t)} s` : `${Math.round(t / 60)} min`);
  if (since !== null && elapsed !== null) parts.push(`${seconds(elapsed)} so far`);
  if (elapsed !== null && fraction > 0.02 && fraction < 1) {
    const left = (elapsed * (1 - fraction)) / fraction;
    parts.push(left < 1 ? "under a second left" : `about ${seconds(left)} left`);
  } else if (fraction < 1) {
    parts.push("time left: known after the first step");
  }
  if (job.message) parts.push(job.message);
  return parts.join(" · ");
}

function jobEnding(job) {
  const error = job.error || {};
  const why = error.message || job.message || "";
  const words = { failed: "failed", cancelled: "was cancelled", interrupted: "was interrupted (the server stopped while it ran)" };
  return `the simulation ${words[job.status] || job.status}${why ? `: ${why}` : ""}`;
}

// ---- formatting -------------------------------------------------------------------------

function fmt(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "n/a";
  const a = Math.abs(x);
  if (a !== 0 && (a >= 1e5 || a < 1e-3)) {
    const [mantissa, exponent] = x.toExponential(digits - 1).split("e");
    return `${Number(mantissa)}e${Number(exponent)}`;
  }
  return Number(x.toPrecision(digits)).toString();
}

const SUPERSCRIPT = { "-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷", 8: "⁸", 9: "⁹" };
function pow10(n) {
  return `10${String(n).split("").map((ch) => SUPERSCRIPT[ch] || ch).join("")}`;
}

// A value with its uncertainty, the value's digits set by the uncertainty's first two.
function withUncertainty(value, error, unit = "") {
  const u = unit ? ` ${unit}` : "";
  if (value === null || value === undefined || !Number.isFinite(value)) return "n/a";
  if (error === null || error === undefined || !Number.isFinite(error) || error <= 0) return `${fmt(value)}${u}`;
  const place = Math.floor(Math.log10(error)) - 1; // the uncertainty's second digit
  const a = Math.abs(value);
  if (a >= 1e-3 && a < 1e5 && place >= -8) {
    if (place > 0) {
      // 30255 ± 220 is 30260 ± 220: no digit finer than the uncertainty's second.
      const step = 10 ** place;
      return `${Math.round(value / step) * step}${u} ± ${Math.round(error / step) * step}${u}`;
    }
    const decimals = Math.max(0, -place);
    return `${value.toFixed(decimals)}${u} ± ${error.toFixed(decimals)}${u}`;
  }
  const exponent = Math.floor(Math.log10(a || error));
  const scale = 10 ** exponent;
  const decimals = Math.max(0, exponent - place);
  return `(${(value / scale).toFixed(decimals)} ± ${(error / scale).toFixed(decimals)}) × ${pow10(exponent)}${u}`;
}

function percent(fraction, error) {
  if (fraction === null || fraction === undefined) return "n/a";
  return withUncertainty(100 * fraction, error === null || error === undefined ? null : 100 * error, "%");
}

function magnitudeText(m, error) {
  if (error !== null && error !== undefined && error < 0.005) return `${m.toFixed(2)} (uncertainty below 0.01 mag)`;
  return withUncertainty(m, error);
}

// Log-axis labels as powers of ten: 10⁻³ at a decade, 2×10⁻³ and 5×10⁻³ between over a short range.
function axisFormatter(logScale) {
  return (u, splits) => {
    const finite = splits.filter((v) => v !== null && Number.isFinite(v));
    if (logScale) {
      const positive = finite.filter((v) => v > 0);
      const decades = positive.length ? Math.log10(Math.max(...positive) / Math.min(...positive)) : 0;
      return splits.map((v) => {
        if (v === null || !(v > 0)) return "";
        const exponent = Math.floor(Math.log10(v) + 1e-9);
        const mantissa = Math.round(v / 10 ** exponent);
        if (mantissa === 1) return pow10(exponent);
        return decades > 2.5 || ![2, 5].includes(mantissa) ? "" : `${mantissa}×${pow10(exponent)}`;
      });
    }
    const big = Math.max(...finite.map(Math.abs));
    const small = Math.min(...finite.filter((v) => v !== 0).map(Math.abs));
    const exponentForm = big >= 1e4 || (small < 1e-2 && small > 0);
    const decimals = Math.max(0, ...finite.map((v) => {
      const text = String(Number(v.toPrecision(6)));
      return text.includes(".") ? text.split(".")[1].length : 0;
    }));
    return splits.map((v) => {
      if (v === null || !Number.isFinite(v)) return "";
      if (v === 0) return "0";
      if (!exponentForm) return v.toFixed(Math.min(decimals, 4));
      const exponent = Math.floor(Math.log10(Math.abs(v)) + 1e-9);
      const mantissa = Number((v / 10 ** exponent).toPrecision(3));
      return mantissa === 1 ? pow10(exponent) : `${mantissa}×${pow10(exponent)}`;
    });
  };
}

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

function logSplits(logScale) {
  const filter = logFilter(logScale);
  return filter ? { filter, ticks: { filter }, grid: { filter } } : {};
}

function plusMinus(value, error) {
  return error === null || error === undefined ? fmt(value) : `${fmt(value)} ± ${fmt(error, 2)}`;
}

function fidelityName(level) {
  return (FIDELITIES[level] || [String(level).replace(/_/g, " ")])[0];
}

function conditionsText(c, extra = {}) {
  if (!c) return "";
  const parts = [
    `${c.band} · detector ${c.sca}`,
    `exposure ${fmt(c.exptime_s ?? c.exptime)} s`,
    c.beta0 !== undefined ? `β₀ = ${fmt(c.beta0)} /e⁻` : null,
    c.full_well_e !== undefined ? `full well ${fmt(c.full_well_e)} e⁻` : null,
    `method: ${fidelityName(c.fidelity)}`,
    c.realizations !== undefined ? `${c.realizations} random centroids` : null,
    c.oversampling !== undefined ? `${c.oversampling}× oversampled, ${c.stamp}×${c.stamp} fine pixels` : null,
    c.ramp ? `up the ramp: ${c.ramp.description}` : null,
    ...Object.entries(extra).map(([k, v]) => `${k} ${v}`),
  ];
  return parts.filter(Boolean).join(" · ");
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (ch) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[ch]);
}

// The server's words in the user's: plain field names, no library phrasing.
function plainWords(text) {
  let out = String(text)
    .replace(/Input should be a valid number(, unable to parse string as a number)?/g, "must be a number")
    .replace(/Input should be a valid integer(, unable to parse string as an integer)?/g, "must be a whole number")
    .replace(/Input should be a valid list/g, "must be a list of numbers")
    .replace(/Input should be/g, "must be")
    .replace(/Extra inputs are not permitted/g, "is not a field the server knows")
    .replace(/\bQ_peak\b/g, "Q (the brightest pixel's charge)")
    .replace(/\bbeta0 x Q\b/g, "β₀ × Q")
    // "≥ 0.000000000000001" as a power of ten.
    .replace(/\b0\.0{4,}\d+/g, (t) => fmt(Number(t)));
  for (const [key, name] of Object.entries(FIELD_NAMES)) {
    if (key.includes("_") || ["sca", "beta0", "exptime", "stars", "betas", "ipc", "bfe", "sed"].includes(key)) {
      out = out.replace(new RegExp(`\\b(scene\\.)?${key}\\b`, "g"), name);
    }
  }
  return out;
}

function fieldName(field) {
  if (!field) return "";
  const key = String(field).replace(/^scene\./, "").replace(/\.\d+$/, "");
  return FIELD_NAMES[key] || key.replace(/_/g, " ");
}

// A number typed by the user, or the raw text so that the server names the field it cannot read.
function numberOrText(text) {
  const trimmed = String(text).trim();
  if (trimmed === "") return null;
  const value = Number(trimmed);
  return Number.isFinite(value) ? value : trimmed;
}

// Precision in the user's terms: "1 %" or "1%" is a percent, a plain number a fraction (0.01).
function readPrecision(text) {
  const trimmed = String(text).trim();
  const match = trimmed.match(/^([-+]?[0-9.]+(?:e[-+]?\d+)?)\s*%$/i);
  if (match) return { value: Number(match[1]) / 100, percent: true };
  if (trimmed === "") return { value: null };
  const value = Number(trimmed);
  return Number.isFinite(value) ? { value, percent: false } : { value: null, error: `"${trimmed.slice(0, 40)}" is not a number or a percent` };
}

function listOf(text) {
  return String(text).split(/[\s,;]+/).filter(Boolean).map(numberOrText);
}

function fillSelect(select, values, chosen, label = (v) => v) {
  select.innerHTML = values.map((v) => `<option value="${escapeHtml(v)}">${escapeHtml(label(v))}</option>`).join("");
  select.value = String(chosen);
}

// Shows every bad field at once, in plain words, and marks each input (and its own message line).
function showError(box, form, error) {
  const errors = (error.errors || []).filter((e) => e && (e.field || e.msg));
  if (errors.length > 1) {
    box.innerHTML = `<div>${errors.length} fields need a look:</div><ul>${errors.map((e) =>
      `<li data-field="${escapeHtml(e.field || "")}">${escapeHtml(e.field ? `${fieldName(e.field)}: ${plainWords(e.msg)}` : plainWords(e.msg))}</li>`).join("")}</ul>`;
  } else {
    box.textContent = error.plain || plainWords(error.message);
  }
  box.hidden = false;
  if (form) {
    form.querySelectorAll("[aria-invalid]").forEach((el) => el.removeAttribute("aria-invalid"));
    for (const field of [error.field, ...errors.map((e) => e.field)]) {
      const name = field ? String(field).replace(/^scene\./, "") : null;
      if (name && form.elements[name] && form.elements[name].setAttribute) form.elements[name].setAttribute("aria-invalid", "true");
    }
  }
}

function clearError(box, form) {
  box.hidden = true;
  box.textContent = "";
  if (form) form.querySelectorAll("[aria-invalid]").forEach((el) => el.removeAttribute("aria-invalid"));
}

function setFieldMessage(name, text) {
  const el = document.getElementById(`msg-${name}`);
  if (el) el.textContent = text || "";
}

// ---- plots --------------------------------------------------------------------------------

function lineSeries(label, color, dash, width = 2) {
  return { label, stroke: color, width, spanGaps: false, dash, points: { show: false } };
}

function pointSeries(label, color, size = 8) {
  return { label, stroke: color, fill: color, width: 0, paths: () => null, points: { show: true, size, fill: color } };
}

// Published values: open circles, so that they read apart from the answer's filled point.
function openPointSeries(label, color, size = 8) {
  return { label, stroke: color, fill: "#fff", width: 0, paths: () => null, points: { show: true, size, width: 1.5, stroke: color, fill: "#fff" } };
}

// Draw (or redraw) plot `name`. `columns` = [{label, x, y, err, fid, series, tag}], joined on x;
// err: 1σ statistical uncertainty per point, fid: relative method uncertainty (both drawn as a band);
// tag: the direct label written at the curve's end. `markers` = [{x, label, color}]: dashed vertical
// lines; `shades` = [{from, to, label, color, hatch}]: x ranges behind the curves. Their names go in
// the key under the plot (never on the canvas, where they covered the answer).
function drawPlot(name, opts) {
  // noAnswer: the plot keeps its curves but its legend reads nothing until hovered (no value may
  // look like the refused answer's, e.g. the previous answer's magnitude).
  const { xLabel, yLabel, columns, logX = false, logY = false, markers = [], shades = [], cursorAt = null, noAnswer = false } = opts;
  const el = document.getElementById(`plot-${name}`);
  const usable = columns.map((c) => {
    const keep = c.x.map((x, i) => x !== null && c.y[i] !== null && c.y[i] !== undefined && (!logX || x > 0) && (!logY || c.y[i] > 0));
    const err = c.err ? c.err.filter((_, i) => keep[i]) : null;
    return { ...c, x: c.x.filter((_, i) => keep[i]), y: c.y.filter((_, i) => keep[i]), err };
  }).filter((c) => c.x.length > 0);
  state.exports[name] = { ...opts, columns: usable };
  if (state.plots[name]) {
    state.plots[name].destroy();
    delete state.plots[name];
  }
  el.innerHTML = "";
  drawKey(name, markers, shades);
  if (usable.length === 0) {
    el.innerHTML = '<p class="muted">nothing to plot for these conditions</p>';
    renderTable(name);
    return;
  }
  const data = uPlot.join(usable.map((c) => {
    const order = c.x.map((_, i) => i).sort((a, b) => c.x[a] - c.x[b]);
    return [order.map((i) => c.x[i]), order.map((i) => c.y[i])];
  }));
  const halfWidths = usable.map((c) => {
    const byX = new Map(c.x.map((x, i) => [x, total(c, i)]));
    return data[0].map((x) => (byX.has(x) ? byX.get(x) : null));
  });
  const xs = data[0];
  const target = cursorAt ?? xs[Math.floor(xs.length / 2)];
  const defaultIdx = xs.reduce((best, x, i) => (Math.abs(x - target) < Math.abs(xs[best] - target) ? i : best), 0);
  const edges = [...markers.map((m) => m.x), ...shades.map((s) => s.to)].filter(Number.isFinite);
  const rangeWith = edges.length;
  // A lone point (an answer without a curve) gets a few magnitudes either side, not uPlot's 0 to 40.
  const lone = !logX && xs.length === 1 ? { range: () => [xs[0] - 3, xs[0] + 3] } : null;
  const options = {
    width: Math.max(280, el.clientWidth || 800),
    height: 320,
    // Room on the right for the last x tick label (the PNG export is this canvas).
    padding: [12, 28, 0, 0],
    scales: {
      x: { time: false, distr: logX ? 3 : 1,
        ...(lone || (rangeWith && !logX ? { range: (u, lo, hi) => [Math.min(lo, ...edges.map((x) => x - 0.5)), hi + 0.9] }
          : (!logX ? { range: (u, lo, hi) => [lo, hi + (hi - lo) * 0.12] } : {}))) },
      y: { distr: logY ? 3 : 1 },
    },
    hooks: {
      drawClear: [(u) => { drawShades(u, shades); drawMarkers(u, markers); drawBands(u, usable, halfWidths); drawWhiskers(u, usable, halfWidths); }],
      draw: [(u) => drawDirectLabels(u, usable)],
    },
    axes: [
      { label: xLabel, values: axisFormatter(logX), space: 60, ...logSplits(logX) },
      { label: yLabel, values: axisFormatter(logY), size: 72, space: 36, ...logSplits(logY) },
    ],
    series: [{ label: xLabel, value: (u, v, si, i) => (i == null && noAnswer ? "–" : fmt(i == null ? u.data[0][defaultIdx] : v)) },
      ...usable.map((c) => {
        const index = new Map(c.x.map((x, i) => [x, i]));
        return { ...c.series, value: (u, v, si, i) => {
          if (i == null && noAnswer) return "–";
          let where = "";
          if (i == null) {
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
  const u = new uPlot(options, data, el);
  el.classList.toggle("legend-void", noAnswer);
  state.plots[name] = u;
  u.defaultIdx = defaultIdx;
  u.halfWidths = halfWidths;
  keyboard(name, el);
  renderTable(name);
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

function describeValue(c, v, j) {
  const stat = j != null && c.err ? c.err[j] : null;
  const fid = c.fid != null ? Math.abs(v) * c.fid : null;
  if (stat == null && fid == null) return fmt(v);
  const parts = [];
  if (stat != null) parts.push(`± ${fmt(stat, 2)} stat`);
  if (fid != null) parts.push(`± ${fmt(fid, 2)} method`);
  return `${fmt(v)} ${parts.join(" ")}`;
}

// Each curve's name written at its faint end, nudged apart so that no two labels overlap.
function drawDirectLabels(u, columns) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  const labels = [];
  columns.forEach((c, k) => {
    if (!c.tag) return;
    const si = k + 1;
    const ys = u.data[si];
    // At the curve's faint end, or (tagAt "start") its bright end, where curves a factor apart are apart.
    let i = c.tagAt === "start" ? 0 : ys.length - 1;
    const step = c.tagAt === "start" ? 1 : -1;
    while (i >= 0 && i < ys.length && ys[i] == null) i += step;
    if (i < 0 || i >= ys.length) return;
    const x = u.valToPos(u.data[0][i], "x", true);
    const y = u.valToPos(ys[i], "y", true);
    if (!Number.isFinite(x) || !Number.isFinite(y)) return;
    labels.push({ x, y, text: c.tag, color: c.series.stroke || "#333", start: c.tagAt === "start" });
  });
  labels.sort((a, b) => a.y - b.y);
  const gap = 13 * ratio;
  const top = u.bbox.top + 6 * ratio;
  const bottom = u.bbox.top + u.bbox.height - 6 * ratio;
  for (let k = 1; k < labels.length; k++) {
    if (labels[k].y - labels[k - 1].y < gap) labels[k].y = labels[k - 1].y + gap;
  }
  // A stack pushed past the bottom of the plot moves up as a whole, and stays below its top.
  const overflow = labels.length ? labels[labels.length - 1].y - bottom : 0;
  if (overflow > 0) labels.forEach((l) => { l.y = Math.max(top, l.y - overflow); });
  for (let k = 1; k < labels.length; k++) {
    if (labels[k].y - labels[k - 1].y < gap) labels[k].y = labels[k - 1].y + gap;
  }
  ctx.save();
  ctx.font = `${11 * ratio}px sans-serif`;
  ctx.textBaseline = "middle";
  for (const l of labels) {
    const width = ctx.measureText(l.text).width;
    const right = u.bbox.left + u.bbox.width;
    const x = l.start ? Math.max(u.bbox.left + 2 * ratio, l.x - width - 6 * ratio) : Math.min(l.x + 4 * ratio, right - width - 2 * ratio);
    ctx.fillStyle = "rgba(255,255,255,0.8)";
    ctx.fillRect(x - 1, l.y - 6 * ratio, width + 2, 12 * ratio);
    ctx.fillStyle = darker(l.color);
    ctx.fillText(l.text, x, l.y);
  }
  ctx.restore();
}

// Labels in a colour dark enough to read on white (the Okabe-Ito yellow and sky blue are not).
function darker(color) {
  const m = String(color).match(/^#([0-9a-f]{6})$/i);
  if (!m) return "#1d2330";
  const n = parseInt(m[1], 16);
  const channel = (shift) => Math.round(((n >> shift) & 255) * 0.6);
  return `rgb(${channel(16)},${channel(8)},${channel(0)})`;
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

// Points (a fresh simulation's) carry their 1σ error as a vertical bar with caps; u.whiskers keeps
// what was drawn (data values) for the plot's table and for tests.
function drawWhiskers(u, columns, halfWidths) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  u.whiskers = [];
  columns.forEach((c, k) => {
    if (c.band !== false || c.answer || !c.err) return;
    const si = k + 1;
    u.data[0].forEach((x, i) => {
      const y = u.data[si][i];
      const h = halfWidths[k][i];
      if (y == null || !h) return;
      const low = u.scales.y.distr === 3 ? Math.max(y - h, y * 1e-3) : y - h;
      const px = u.valToPos(x, "x", true);
      const [top, bottom] = [u.valToPos(y + h, "y", true), u.valToPos(low, "y", true)];
      ctx.save();
      ctx.strokeStyle = c.series.stroke || "#333";
      ctx.lineWidth = 1.5 * ratio;
      ctx.beginPath();
      ctx.moveTo(px, top); ctx.lineTo(px, bottom);
      ctx.moveTo(px - 4 * ratio, top); ctx.lineTo(px + 4 * ratio, top);
      ctx.moveTo(px - 4 * ratio, bottom); ctx.lineTo(px + 4 * ratio, bottom);
      ctx.stroke();
      ctx.restore();
      u.whiskers.push({ label: c.label, x, y, half: h });
    });
  });
}

function drawShades(u, shades) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  shades.forEach((s) => {
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
  });
}

function drawMarkers(u, markers) {
  const ctx = u.ctx;
  const ratio = window.devicePixelRatio || 1;
  markers.forEach((m) => {
    const x = u.valToPos(m.x, "x", true);
    if (!Number.isFinite(x)) return;
    ctx.save();
    ctx.strokeStyle = m.color;
    ctx.lineWidth = 1.5 * ratio;
    ctx.setLineDash((m.dash || [6, 4]).map((d) => d * ratio));
    ctx.beginPath();
    ctx.moveTo(x, u.bbox.top);
    ctx.lineTo(x, u.bbox.top + u.bbox.height);
    ctx.stroke();
    ctx.restore();
  });
}

// The key under a plot: shaded ranges and limit lines, named in HTML (wraps on a phone).
function drawKey(name, markers, shades) {
  const el = document.getElementById(`key-${name}`);
  if (!el) return;
  const items = [
    ...shades.map((s) => `<span class="key-item"><span class="swatch${s.hatch ? " hatch" : ""}" style="background-color:${s.color}"></span>${escapeHtml(s.label)}</span>`),
    ...markers.map((m) => `<span class="key-item"><span class="swatch line" style="border-color:${m.color}"></span>${escapeHtml(m.label)}: m = ${fmt(m.x, 4)}</span>`),
  ];
  el.innerHTML = items.join("");
}

// "no answer" over a plot that keeps its axes and curves.
function setNoAnswer(name, reason, prefix = "no answer: ") {
  const el = document.getElementById(`plot-${name}`);
  el.querySelectorAll(".no-answer").forEach((n) => n.remove());
  el.dataset.answer = reason ? "none" : el.dataset.answer;
  if (!reason) return;
  const note = document.createElement("div");
  note.className = "no-answer";
  note.dataset.testid = "no-answer";
  note.textContent = `${prefix}${reason}`;
  el.appendChild(note);
}

// Arrow keys move the reading along the x axis (Shift: five steps); Home and End jump to the ends.
function keyboard(name, el) {
  el.tabIndex = 0;
  el.setAttribute("role", "group");
  el.setAttribute("aria-label", `${document.getElementById(`plot-${name}`).closest("figure").querySelector("h3")?.textContent || name} plot: arrow keys read values`);
  if (el.dataset.keys) return;
  el.dataset.keys = "on";
  el.addEventListener("keydown", (event) => {
    const u = state.plots[name];
    if (!u) return;
    const n = u.data[0].length;
    let idx = state.kbIdx[name] ?? u.defaultIdx;
    const step = event.shiftKey ? 5 : 1;
    if (event.key === "ArrowRight") idx = Math.min(n - 1, idx + step);
    else if (event.key === "ArrowLeft") idx = Math.max(0, idx - step);
    else if (event.key === "Home") idx = 0;
    else if (event.key === "End") idx = n - 1;
    else return;
    event.preventDefault();
    state.kbIdx[name] = idx;
    let si = 1;
    while (si < u.data.length && u.data[si][idx] == null) si++;
    const y = si < u.data.length ? u.data[si][idx] : null;
    const left = u.valToPos(u.data[0][idx], "x");
    const top = y == null ? u.bbox.height / 2 / (window.devicePixelRatio || 1) : u.valToPos(y, "y");
    u.setCursor({ left, top });
  });
  el.addEventListener("blur", () => { delete state.kbIdx[name]; });
}

// A table of every plotted value under the plot, folded away until asked for.
function renderTable(name) {
  const plot = state.exports[name];
  const figure = document.getElementById(`plot-${name}`).closest("figure");
  let details = figure.querySelector("details.table-view");
  if (!details) {
    details = document.createElement("details");
    details.className = "table-view";
    details.innerHTML = `<summary>Table of values</summary><div class="table-wrap" tabindex="0" aria-label="table of the plotted values (scrolls sideways)"></div>`;
    const key = document.getElementById(`key-${name}`);
    (key || document.getElementById(`plot-${name}`)).after(details);
  }
  const wrap = details.querySelector(".table-wrap");
  if (!plot || !plot.columns.length) {
    wrap.innerHTML = '<p class="muted">no values</p>';
    return;
  }
  const xs = [...new Set(plot.columns.flatMap((c) => c.x))].sort((a, b) => a - b);
  const lookup = plot.columns.map((c) => new Map(c.x.map((x, i) => [x, [c.y[i], c.err ? c.err[i] : null]])));
  const head = `<tr><th scope="col">${escapeHtml(plot.xLabel)}</th>${plot.columns.map((c) => `<th scope="col">${escapeHtml(c.label)}</th>`).join("")}</tr>`;
  const rows = xs.map((x) => `<tr><th scope="row">${fmt(x)}</th>${lookup.map((m) => {
    const v = m.get(x);
    return `<td>${v ? escapeHtml(v[1] != null ? plusMinus(v[0], v[1]) : fmt(v[0])) : ""}</td>`;
  }).join("")}</tr>`).join("");
  wrap.innerHTML = `<table><caption>${escapeHtml(plot.yLabel)} (± statistical 1σ)</caption><thead>${head}</thead><tbody>${rows}</tbody></table>`;
  markScrollable(wrap);
}

function exportCsv(name) {
  const plot = state.exports[name];
  if (!plot) return;
  // Downloads hold fractions: a percent axis is written as a fraction, and says so.
  const percentAxis = /\[%\]/.test(plot.yLabel);
  const scale = percentAxis ? 0.01 : 1;
  const yLabel = percentAxis ? plot.yLabel.replace("[%]", "[fraction]") : plot.yLabel;
  const quote = (t) => `"${String(t).replace(/"/g, "'")}"`;
  const meta = state.meta ? `# nlpsf ${state.meta.code_version}; optical data: ${state.meta.data_version}` : "# nlpsf";
  const lines = [`# ${plot.title.replace(/\n/g, " · ")}`, meta, `# link: ${location.href}`,
    `# columns: series; x = ${plot.xLabel}; y = ${yLabel}; uncertainty = the 1-sigma statistical part of y, same unit` +
    (percentAxis ? " (the page shows y in percent)" : ""),
    `series,${quote(plot.xLabel)},${quote(yLabel)},uncertainty`];
  for (const c of plot.columns) {
    c.x.forEach((x, i) => lines.push(`${quote(c.label)},${x},${c.y[i] === null ? "" : c.y[i] * scale},` +
      `${c.err && c.err[i] != null ? c.err[i] * scale : ""}`));
  }
  for (const m of plot.markers || []) lines.push(`${quote(m.label)},${m.x},,`);
  for (const sh of plot.shades || []) lines.push(`${quote(sh.label)},${sh.to},,`);
  downloadText(`${plotFileName(name)}.csv`, lines.join("\n") + "\n", "text/csv");
}

// Distinct names: which plot, and the choices that made it.
function plotFileName(name) {
  const v = (id) => (document.getElementById(id) ? document.getElementById(id).value : "");
  const s = state.lastSolution;
  const parts = {
    req: s ? [s.band, `sca${s.sca}`, s.metric, s.mode] : [],
    calc: s ? [s.band, `sca${s.sca}`, s.metric, s.mode] : [],
    slopes: [v("slopes-metric"), v("slopes-mode"), `sca${v("solve-sca")}`],
    beta: [v("beta-band"), v("beta-metric"), `m${v("beta-magnitude")}`],
    sigma: [v("sigma-band"), v("sigma-metric"), `m${v("sigma-magnitude")}`],
  }[name] || [];
  return ["nlpsf-plot", name, ...parts].filter(Boolean).join("-").replace(/[^A-Za-z0-9._-]/g, "");
}

function exportPng(name) {
  const u = state.plots[name];
  const plot = state.exports[name];
  if (!u || !plot) return;
  const source = u.ctx.canvas;
  const scale = Math.max(1, source.width / u.width);
  const font = 14 * scale;
  const row = 20 * scale;
  const entries = [
    ...plot.columns.map((c) => ({ label: c.label, color: c.series.stroke || "#000", dash: c.series.dash, point: !c.series.width })),
    ...(plot.markers || []).map((m) => ({ label: `${m.label}: m = ${fmt(m.x)}`, color: m.color, dash: [6, 4] })),
    ...(plot.shades || []).map((s) => ({ label: s.label, color: s.hatch || s.color, fill: s.color })),
  ];
  const canvas = document.createElement("canvas");
  const ctx = canvas.getContext("2d");
  ctx.font = `${font}px sans-serif`;
  // Title lines wrapped at the image's width: nothing is cut.
  const titleLines = plot.title.split("\n").flatMap((line) => wrapText(ctx, line, source.width - 16 * scale));
  const width = Math.min(source.width - 16 * scale, Math.max(...entries.map((e) => ctx.measureText(e.label).width)) + 48 * scale);
  const perRow = Math.max(1, Math.floor((source.width - 16 * scale) / width));
  // Each key entry's label wrapped to its column: nothing is cut at the image's edge.
  entries.forEach((e) => { e.lines = wrapText(ctx, e.label, width - 44 * scale); });
  const rows = [];
  for (let i = 0; i < entries.length; i += perRow) rows.push(Math.max(...entries.slice(i, i + perRow).map((e) => e.lines.length)));
  const top = row * titleLines.length + 10 * scale;
  const bottom = row * rows.reduce((a, n) => a + n, 0) + 12 * scale;
  canvas.width = source.width;
  canvas.height = source.height + top + bottom;
  ctx.fillStyle = "#fff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#1d2330";
  ctx.font = `${font}px sans-serif`;
  titleLines.forEach((line, i) => ctx.fillText(line, 8 * scale, row * (i + 1)));
  ctx.drawImage(source, 0, top);
  entries.forEach((e, i) => {
    const r = Math.floor(i / perRow);
    const x = 8 * scale + (i % perRow) * width;
    const y = top + source.height + row * (rows.slice(0, r).reduce((a, n) => a + n, 0) + 1);
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
    e.lines.forEach((line, k) => ctx.fillText(line, x + 36 * scale, y + k * row));
  });
  // Synchronously (not canvas.toBlob): the download must start within the click, or the browser
  // counts it as an automatic download and may block it.
  const bytes = atob(canvas.toDataURL("image/png").split(",")[1]);
  const buffer = new Uint8Array(bytes.length);
  for (let i = 0; i < bytes.length; i++) buffer[i] = bytes.charCodeAt(i);
  downloadBlob(`${plotFileName(name)}.png`, new Blob([buffer], { type: "image/png" }));
}

// A line of text broken at spaces into lines no wider than `width` on `ctx`.
function wrapText(ctx, text, width) {
  const lines = [];
  let line = "";
  for (const word of String(text).split(" ")) {
    const next = line ? `${line} ${word}` : word;
    if (line && ctx.measureText(next).width > width) {
      lines.push(line);
      line = word;
    } else {
      line = next;
    }
  }
  if (line) lines.push(line);
  return lines;
}

function download(filename, url) {
  const a = document.createElement("a");
  a.href = url;
  a.download = filename;
  document.body.appendChild(a);
  a.click();
  a.remove();
}

// Blob URLs, not data: URLs: no size limit, and released once the download has started.
function downloadBlob(filename, blob) {
  const url = URL.createObjectURL(blob);
  download(filename, url);
  setTimeout(() => URL.revokeObjectURL(url), 10_000);
}

function downloadText(filename, text, type) {
  downloadBlob(filename, new Blob([text], { type: `${type};charset=utf-8` }));
}

// A wide table scrolls sideways; a shadow at its edge and a line of text say so.
function markScrollable(wrap) {
  const update = () => {
    const more = wrap.scrollWidth - wrap.clientWidth - wrap.scrollLeft > 2;
    wrap.classList.toggle("more-right", more);
    wrap.classList.toggle("more-left", wrap.scrollLeft > 2);
    let cue = wrap.previousElementSibling;
    if (!cue || !cue.classList.contains("scroll-cue")) {
      cue = document.createElement("p");
      cue.className = "scroll-cue";
      cue.setAttribute("aria-hidden", "true");
      wrap.before(cue);
    }
    cue.textContent = wrap.scrollWidth > wrap.clientWidth + 2 ? "scroll sideways for more columns →" : "";
  };
  if (!wrap.dataset.cue) {
    wrap.dataset.cue = "on";
    wrap.addEventListener("scroll", update, { passive: true });
    window.addEventListener("resize", update);
  }
  requestAnimationFrame(update);
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

// ---- state in the URL -------------------------------------------------------------------------

const URL_FIELDS = {
  "solve-form": ["band", "sca", "metric", "mode", "scene", "position", "beta0", "exptime", "full_well", "fidelity", "ma_table", "ramp",
    "ramp_fit", "stars", "shear_m", "shear_c", "size_ratio", "precision", "tolerance", "magnitude"],
  "scene-form": ["preset", "sed", "jitter", "charge_diffusion", "ipc", "ipc_order", "nl_coefficients", "bfe", "background"],
};
const CHECKBOXES = ["beta-log", "sigma-log", "paper-overlay", "scene-use", "calc-paper"];
const URL_CONTROLS = ["slopes-metric", "slopes-mode", "beta-band", "beta-metric", "beta-magnitude", "sigma-band", "sigma-metric",
  "sigma-magnitude", "req-preset"];

function stateToUrl() {
  const q = new URLSearchParams();
  const solveForm = document.getElementById("solve-form");
  const unknown = solveForm.elements.solve_for.value;
  q.set("solve_for", unknown);
  for (const [formId, names] of Object.entries(URL_FIELDS)) {
    const form = document.getElementById(formId);
    const prefix = formId === "scene-form" ? "scene." : "";
    for (const name of names) {
      const input = form.elements[name];
      if (!input || (formId === "solve-form" && name === unknown)) continue;
      if (formId === "solve-form" && name === "tolerance" && input.dataset.derived === "true") continue;
      const value = String(input.value).trim();
      if (value !== "") q.set(prefix + name, value);
    }
  }
  for (const id of URL_CONTROLS) {
    const el = document.getElementById(id);
    if (el && el.value !== "") q.set(id, el.value);
  }
  for (const id of CHECKBOXES) {
    if (document.getElementById(id).checked) q.set(id, "1");
  }
  history.replaceState(null, "", `${location.pathname}?${q.toString()}`);
}

function stateFromUrl() {
  const q = new URLSearchParams(location.search);
  if (![...q.keys()].length) return false;
  const solveForm = document.getElementById("solve-form");
  const unknown = q.get("solve_for");
  if (["precision", "tolerance", "magnitude"].includes(unknown)) solveForm.elements.solve_for.value = unknown;
  for (const [formId, names] of Object.entries(URL_FIELDS)) {
    const form = document.getElementById(formId);
    const prefix = formId === "scene-form" ? "scene." : "";
    for (const name of names) {
      const input = form.elements[name];
      if (!input) continue;
      if (q.has(prefix + name)) input.value = q.get(prefix + name);
      else if (formId === "solve-form" && ["shear_m", "shear_c", "size_ratio"].includes(name)) input.value = "";
    }
  }
  // The readout select restores its own inputs (reads, fit).
  const readout = solveForm.elements.ma_table;
  if (q.has("ma_table")) readout.value = q.get("ma_table");
  readoutChanged("solve", false);
  if (q.has("ramp")) solveForm.elements.ramp.value = q.get("ramp");
  if (q.has("ramp_fit")) solveForm.elements.ramp_fit.value = q.get("ramp_fit");
  for (const id of URL_CONTROLS) {
    const el = document.getElementById(id);
    if (el && q.has(id)) el.value = q.get(id);
  }
  for (const id of CHECKBOXES) document.getElementById(id).checked = q.get(id) === "1";
  // Links from before the position moved to the calculator.
  if (!q.has("position") && q.has("scene.position")) solveForm.elements.position.value = q.get("scene.position");
  exposurePlaceholder();
  showPresetSource();
  return true;
}

async function copyLink() {
  stateToUrl();
  const status = document.getElementById("link-status");
  try {
    await navigator.clipboard.writeText(location.href);
    status.textContent = "link copied";
  } catch (_) {
    // No clipboard (an insecure origin or a denied permission): show the link to copy by hand.
    status.innerHTML = `copy this link: <input class="link-text" readonly value="${escapeHtml(location.href)}" aria-label="link to this view">`;
    status.querySelector("input").select();
  }
  status.dataset.link = location.href;
}

// ---- readout: final frame, uniform ramp or an MA table ------------------------------------------

function fillReadout(group) {
  const select = document.getElementById(`${group}-readout`);
  const options = [["final", "the scene's readout"], ["uniform", "uniform ramp, N reads"],
    ...(state.meta.ma_tables || []).map((t) => [`table:${t.name}`,
      `MA table ${t.name} (${t.resultants} resultants, ${fmt(t.last_read_s)} s)`])];
  select.innerHTML = options.map(([v, l]) => `<option value="${escapeHtml(v)}">${escapeHtml(l)}</option>`).join("");
  // "": the scene's own fit (the Roman default's likelihood fit; the paper's ordinary least squares).
  fillSelect(document.getElementById(`${group}-ramp_fit`), ["", ...(state.meta.ramp_fits || ["ols"])], "",
    (f) => (f === "" ? "the scene's fit" : f === "ols" ? "ordinary least squares" : "optimal (read + Poisson noise weights)"));
  select.addEventListener("change", () => readoutChanged(group));
}

function readoutChanged(group, setExposure = true) {
  const choice = document.getElementById(`${group}-readout`).value;
  const reads = document.getElementById(`${group}-ramp`);
  const fit = document.getElementById(`${group}-ramp_fit`);
  reads.disabled = choice !== "uniform";
  fit.disabled = choice === "final";
  // A greyed field shows what the answer uses, never a value it does not.
  if (choice === "uniform") {
    if (reads.value.trim() === "") reads.value = "8";
  } else {
    reads.value = "";
    reads.placeholder = readsPlaceholder(group, choice);
  }
  if (choice === "final") fit.value = "";
  if (!setExposure) return;
  // An MA table's exposure is its last read; leaving a table restores the exposure the API fills in.
  const exposure = document.getElementById(`${group}-exptime`);
  const durations = (state.meta.ma_tables || []).map((t) => String(t.last_read_s));
  const table = (state.meta.ma_tables || []).find((t) => `table:${t.name}` === choice);
  if (table) exposure.value = String(table.last_read_s);
  else if (durations.includes(exposure.value.trim())) exposure.value = "";
}

// What the readout reads when the reads box is greyed: the scene's readout, or the chosen MA table's.
function readsPlaceholder(group, choice) {
  const tables = (state.meta && state.meta.ma_tables) || [];
  const table = tables.find((t) => `table:${t.name}` === choice);
  if (table) return `${table.reads} reads`;
  const scene = group === "solve" ? document.getElementById("solve-scene").value : "";
  if (scene === "paper") return "final frame";
  const roman = (state.meta && state.meta.defaults.scene_exptime.roman) || null;
  const own = tables.find((t) => roman !== null && Math.abs(t.last_read_s - roman) < 1e-6);
  return own ? `${own.reads} reads` : "the scene's";
}

// The exposure box left empty sends no exptime: the API fills the scene's (GET /meta's
// defaults.scene_exptime: the Roman default's HLWAS table, the paper's final frame); the
// placeholder says which.
function exposurePlaceholder() {
  const scene = document.getElementById("solve-scene").value || "roman";
  const exposures = (state.meta && state.meta.defaults.scene_exptime) || {};
  const name = scene === "paper" ? "paper" : "Roman default";
  const input = document.getElementById("solve-exptime");
  input.placeholder = exposures[scene] !== undefined ? `${fmt(exposures[scene], 6)} (${name === "paper" ? "paper" : "Roman"})` : "the scene's";
  readoutChanged("solve", false);
}

function readoutFields(group) {
  const choice = document.getElementById(`${group}-readout`).value;
  const fit = document.getElementById(`${group}-ramp_fit`).value;
  const fitField = fit ? { ramp_fit: fit } : {};  // none: the scene's fit
  if (choice === "uniform") return { ramp: numberOrText(document.getElementById(`${group}-ramp`).value), ...fitField };
  if (choice.startsWith("table:")) return { ma_table: choice.slice(6), ...fitField };
  return {};
}

// ---- requirement presets ------------------------------------------------------------------------

function fillPresets() {
  const select = document.getElementById("req-preset");
  for (const p of state.presets.presets) {
    const option = document.createElement("option");
    option.value = p.id;
    option.textContent = p.name;
    select.appendChild(option);
  }
  select.addEventListener("change", () => {
    const preset = state.presets.presets.find((p) => p.id === select.value);
    if (preset) applyPreset(preset);
    showPresetSource();
  });
}

function applyPreset(preset) {
  const form = document.getElementById("solve-form");
  for (const name of ["shear_m", "shear_c", "size_ratio"]) form.elements[name].value = "";
  // The preset's tolerance replaces whatever was typed before a budget greyed the box.
  delete form.elements.tolerance.dataset.typed;
  delete form.elements.tolerance.dataset.shown;
  for (const [name, value] of Object.entries(preset.fields)) {
    if (name === "tolerance") {
      form.elements.tolerance.value = String(value);
      form.elements.tolerance.dataset.derived = "false";
    } else {
      form.elements[name].value = String(value);
    }
  }
  if (form.elements.solve_for.value === "tolerance") form.elements.solve_for.value = "precision";
  updateUnknown();
  // A preset is a question: it is answered at once (the old answer greys meanwhile, the budget's T follows).
  solve(null);
}

function showPresetSource() {
  const preset = (state.presets ? state.presets.presets : []).find((p) => p.id === document.getElementById("req-preset").value);
  document.getElementById("preset-source").textContent = preset ? `Source: ${preset.source}. NL's share: ${preset.share}.` : "";
}

// ---- calculator -------------------------------------------------------------------------------

function shearGiven() {
  const form = document.getElementById("solve-form");
  return ["shear_m", "shear_c"].some((n) => form.elements[n].value.trim() !== "");
}

function updateUnknown() {
  const form = document.getElementById("solve-form");
  const unknown = form.elements.solve_for.value;
  const derived = shearGiven();
  for (const name of ["precision", "tolerance", "magnitude"]) {
    const input = form.elements[name];
    const solved = name === unknown;
    // A shear budget sets T: the box shows the T it implies, greyed, and is not a given.
    const fromBudget = name === "tolerance" && derived && !solved;
    input.disabled = solved || fromBudget;
    input.classList.toggle("derived", fromBudget);
    input.dataset.derived = fromBudget ? "true" : "false";
    if (solved) input.value = "";
    if (fromBudget && !input.dataset.typed) input.dataset.typed = input.value;
    if (!fromBudget && input.dataset.typed !== undefined && name === "tolerance") {
      if (input.value === "" || input.dataset.shown === "budget") input.value = input.dataset.typed;
      delete input.dataset.typed;
      delete input.dataset.shown;
    }
    setFieldMessage(name, fromBudget ? "set by the shear budget" : "");
  }
  precisionHint();
}

function precisionHint() {
  const input = document.getElementById("solve-precision");
  const hint = document.getElementById("hint-precision");
  if (input.disabled) {
    hint.textContent = "";
    return;
  }
  const read = readPrecision(input.value);
  hint.textContent = read.value === null ? "" : `read as ${fmt(100 * read.value, 4)} % (fraction ${fmt(read.value, 4)})`;
}

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
    if (name === "precision") {
      const read = readPrecision(text);
      if (read.error) errors.push({ field: name, msg: read.error });
      else values[name] = read.value;
      continue;
    }
    const value = Number(text);
    if (!Number.isFinite(value)) errors.push({ field: name, msg: `"${text.slice(0, 40)}" is not a number` });
    else values[name] = value;
  }
  return [values, errors];
}

// The question the form asks, as POST /solve's body, with every field the page can check itself.
function questionBody() {
  const form = document.getElementById("solve-form");
  const unknown = form.elements.solve_for.value;
  const budget = shearGiven();
  const givens = ["precision", "tolerance", "magnitude"].filter((n) => n !== unknown && !(n === "tolerance" && budget));
  const [numbers, errors] = readNumbers(form, ["beta0", "exptime", "full_well", "stars", ...givens, "shear_m", "shear_c", "size_ratio"],
    ["exptime", "shear_m", "shear_c", "size_ratio"]);
  if (budget && form.elements.size_ratio.value.trim() === "") {
    errors.push({ field: "size_ratio", msg: "a shear budget needs the galaxy-to-PSF size ratio" });
  }
  for (const e of errors) {
    if (givens.includes(e.field) && e.msg === "enter a value") e.msg = "enter a value (give two of precision, tolerance, magnitude)";
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
  const scene = calculatorScene();
  if (scene !== null) body.scene = scene;
  return { body, errors, unknown };
}

// The calculator's scene: a preset's name, the Scene section's fields, and the position (X,Y in pixels).
// None of them: the Roman default over the whole SCA (the API's default).
function calculatorScene() {
  const form = document.getElementById("solve-form");
  const choice = form.elements.scene.value;
  const text = form.elements.position.value.trim();
  const position = text ? listOf(text) : null;
  if (choice === "custom") {
    const scene = sceneBody() || {};
    if (position) scene.position = position;
    return scene;
  }
  if (!position) return choice || null;
  return { ...(choice ? { preset: choice } : {}), position };
}

// A question in words (for the note on an answer that is out of date).
function questionText(body) {
  if (!body) return "an earlier question";
  const given = [];
  if (body.precision !== undefined) given.push(`p = ${fmt(100 * body.precision, 4)} %`);
  if (body.tolerance !== undefined) given.push(`T = ${fmt(body.tolerance)}`);
  if (body.shear_m !== undefined) given.push(`|m| = ${fmt(body.shear_m)}`);
  if (body.shear_c !== undefined) given.push(`|c| = ${fmt(body.shear_c)}`);
  if (body.magnitude !== undefined) given.push(`m = ${fmt(body.magnitude)}`);
  const scene = body.scene;
  const named = { paper: "the paper's scene", "galsim-roman": "GalSim's Roman constants" };
  let where = typeof scene === "string" ? named[scene] || scene
    : scene ? `${named[scene.preset] || (scene.preset ? scene.preset : "the Roman default")}${Object.keys(scene).some((k) => !["preset", "position"].includes(k)) ? " with changes" : ""}`
      : "the Roman default";
  where += scene && scene.position ? ` at (${scene.position.join(", ")})` : (!scene || scene === "roman" || (scene && !scene.preset)) ? " over the whole SCA" : "";
  const extra = [body.exptime !== undefined ? `${fmt(body.exptime)} s` : null, body.beta0 !== 5e-7 ? `β₀ = ${fmt(body.beta0)}` : null]
    .filter(Boolean);
  return `${body.band} SCA ${body.sca}, ${METRIC_LABEL[body.metric] || body.metric} ${body.mode}, ${given.join(", ")}, ${where}` +
    (extra.length ? `, ${extra.join(", ")}` : "");
}

// The answer on screen either answers the question asked (current) or is greyed with what it answered.
function setStale(reason) {
  const box = document.getElementById("solve-result");
  const top = document.getElementById("top-answer");
  const stale = Boolean(reason) && Boolean(state.lastSolution);
  state.current = Boolean(state.lastSolution) && !reason;
  box.classList.toggle("stale", stale);
  top.classList.toggle("stale", Boolean(reason));
  const mark = top.querySelector(".stale-mark");
  if (reason && state.lastSolution && !mark) {
    top.insertAdjacentHTML("afterbegin", '<strong class="stale-mark">Out of date (an earlier question\'s): </strong>');
  } else if (!reason && mark) {
    mark.remove();
  }
  let note = box.querySelector(".stale-note");
  if (stale) {
    if (!note) {
      note = document.createElement("p");
      note.className = "stale-note";
      note.dataset.testid = "stale-note";
      box.prepend(note);
    }
    note.textContent = `Out of date — this is the answer to: ${questionText(state.lastRequest)}. ${reason}`;
    box.setAttribute("aria-busy", state.solving ? "true" : "false");
  } else if (note) {
    note.remove();
    box.removeAttribute("aria-busy");
  }
  for (const figure of document.querySelectorAll("#calculator figure.plot")) figure.classList.toggle("stale", Boolean(reason));
  // Pin and the downloads act only on an answer to the question asked.
  for (const id of ["pin-answer", "download-json", "download-ecsv"]) document.getElementById(id).disabled = !state.current;
}

// An edit of the form after an answer: the answer no longer answers what the form says.
function formEdited() {
  if (!state.lastSolution || state.solving) return;
  const { body } = questionBody();
  if (JSON.stringify(body) !== JSON.stringify(state.lastRequest)) {
    setStale("The inputs have changed since: Solve to answer them.");
  } else if (!state.failed) {
    setStale(null);
  }
}

function showSolveProgress(job) {
  const row = document.getElementById("solve-progress-row");
  if (!job) {
    row.hidden = true;
    return;
  }
  row.hidden = false;
  document.getElementById("solve-progress").value = job.progress || 0;
  document.getElementById("solve-progress-text").textContent = `Simulating the answer: ${progressText(job, state.solveStarted || null)}`;
}

async function solve(event) {
  if (event) event.preventDefault();
  const form = document.getElementById("solve-form");
  const errorBox = document.getElementById("solve-error");
  clearError(errorBox, form);
  for (const name of ["precision", "tolerance", "magnitude"]) setFieldMessage(name, "");
  const { body, errors } = questionBody();
  // The URL records the question as it is asked: a reload while it is answered asks it again.
  stateToUrl();
  if (errors.length) {
    failAnswer(new ApiError(`${fieldName(errors[0].field)}: ${errors[0].msg}`, errors[0].field, 0, errors), errors[0].msg);
    return;
  }
  const button = document.getElementById("solve-button");
  button.disabled = true;
  button.textContent = "Solving…";
  state.asked = body;
  state.solving = true;
  // Until the new answer comes, the old one is greyed and says what it answered.
  setStale(`Waiting for the answer to: ${questionText(body)}.`);
  // A Roman default answer can be a job that takes seconds: an answer to an older question that
  // arrives after a newer one was asked is dropped, never shown over it.
  const asked = (state.solveSeq = (state.solveSeq || 0) + 1);
  state.solveStarted = Date.now();
  const cancel = document.getElementById("solve-cancel");
  try {
    // wait=1: an answer that needs a simulation comes back as its job after a second, so its progress shows.
    const s = await api("/solve?wait=1", { method: "POST", body: JSON.stringify(body), followJob: true,
      onJob: (location) => {
        button.textContent = "Simulating…";
        cancel.onclick = () => fetch(location, { method: "DELETE" }).catch(() => {});
        showSolveProgress({ status: "queued", progress: 0 });
      },
      onProgress: (job) => { if (asked === state.solveSeq) showSolveProgress(job); } });
    if (asked !== state.solveSeq) return;
    state.solving = false;
    state.failed = false;
    state.lastRequest = body;
    showAnswer(s);
    setStale(null);
    await drawAnswerPlots(body, s);
    // The slopes' legend reads at the answer's magnitude, for the answer's scene.
    drawSlopes().catch(() => {});
  } catch (error) {
    if (asked !== state.solveSeq) return;
    state.solving = false;
    if (error.unreachable) connection.lost("solve", () => solve(null));
    await failAnswer(error, null, body);
  } finally {
    if (asked === state.solveSeq) {
      state.solving = false;
      button.disabled = false;
      button.textContent = "Solve";
      showSolveProgress(null);
    }
  }
}

// A number in a library sentence to the digits it supports (a background of 76.6709 e- is 76.7 e-).
function roundNumbers(text) {
  return String(text).replace(/\d+\.\d{3,}/g, (t) => String(Number(Number(t).toPrecision(3))));
}

// The precision range over the SCA's positions in percent (the library's flag words it as fractions).
function scaRangeText(s) {
  const range = s.conditions && s.conditions.sca_range;
  if (!range) return null;
  const most = range.most_demanding;
  const least = range.least_demanding;
  const solved = range.solved_for;
  const value = (v) => (v === null || v === undefined ? "n/a" : solved === "precision" ? (v >= 1 ? "no constraint" : percent(v, s.uncertainty).split(" ± ")[0])
    : solved === "magnitude" ? `m = ${fmt(v, 4)}` : fmt(v, 4));
  return `no position given: the answer holds everywhere on SCA ${s.sca}, the most demanding of its ${range.nodes.length} ` +
    `field-grid positions, pixel (${most.position.join(", ")}): ${value(most[solved])}; the least demanding, pixel ` +
    `(${least.position.join(", ")}): ${value(least[solved])}. Give a position for the answer at one star.`;
}

function isExtrapolated(s) {
  return (s.flag_codes || []).includes("extrapolated_answer");
}

// c(m) with its whole uncertainty: the statistical part and the method's (relative, from the library).
function slopeText(s, methodRelative) {
  if (s.slope === null || s.slope === undefined) return "slope c(m): n/a";
  const stat = s.slope_uncertainty || 0;
  const method = methodRelative !== null && methodRelative !== undefined ? Math.abs(s.slope) * methodRelative : null;
  const total = method !== null ? Math.hypot(stat, method) : stat;
  const parts = [`statistical ± ${fmt(stat, 2)}`];
  if (method !== null) parts.push(`method ± ${fmt(method, 2)}`);
  return `slope c(m) = ${withUncertainty(s.slope, total, "e⁻")} (${parts.join(", ")}${method === null ? "; method part with the curve" : ""})`;
}

function methodRelativeOf(s) {
  // p ∝ 1/|c| and T ∝ |c|: the method part of the answer relative to it is the slope's.
  if (s.uncertainty_fidelity === null || s.uncertainty_fidelity === undefined) return null;
  if (s.solved_for === "precision" && s.precision > 0 && Number.isFinite(s.precision)) return s.uncertainty_fidelity / s.precision;
  if (s.solved_for === "tolerance" && s.tolerance > 0) return s.uncertainty_fidelity / s.tolerance;
  return state.curves && state.curves.curves ? state.curves.curves.method_relative : null;
}

function saturationText(s) {
  const ramp = s.conditions.ramp;
  const range = s.conditions.sca_range ? " at the answer's position" : "";
  if (!ramp) return `saturation: stars brighter than m = ${fmt(s.saturation_magnitude, 4)} pass the full well in the final frame${range}`;
  return `saturation for this readout: m = ${fmt(s.saturation_magnitude, 4)}${range} (${limitResultantText(ramp)}); ` +
    `the final frame's limit m = ${fmt(s.final_frame_saturation_magnitude, 4)} is where the brightest pixel's last resultants start to saturate (they are dropped from the fit)`;
}

function showAnswer(s) {
  const form = document.getElementById("solve-form");
  const resultBox = document.getElementById("solve-result");
  const unknown = s.solved_for;
  const solvedInput = form.elements[unknown];
  solvedInput.classList.remove("failed");
  solvedInput.placeholder = "";
  // The box holds the value to the digits its uncertainty allows (the headline gives the ±).
  if (unknown === "precision") solvedInput.value = s.precision >= 1 ? "no constraint" : percent(s.precision, s.uncertainty).split(" ± ")[0];
  else if (unknown === "magnitude") solvedInput.value = s.magnitude.toFixed(2);
  else solvedInput.value = withUncertainty(s.tolerance, s.uncertainty).split(" ± ")[0].replace(/^\(/, "") + tolSuffix(s);
  const tol = form.elements.tolerance;
  if (s.shear && s.shear.given !== "tolerance" && tol.dataset.derived === "true") {
    tol.value = fmt(s.shear.tolerance, 3);
    tol.dataset.shown = "budget";
  }
  const noConstraint = unknown === "precision" && s.precision >= 1;
  const uncertaintyParts = [["statistical", s.uncertainty_statistical], ["method", s.uncertainty_fidelity],
    ["optical model", s.uncertainty_optical_model], ["effects not modelled", s.uncertainty_model]]
    .filter(([, v]) => v !== null && v !== undefined);
  const scale = unknown === "precision" ? 100 : 1;
  const unit = unknown === "precision" ? " %" : unknown === "magnitude" ? " mag" : "";
  const flags = (s.flags || []).map((f, k) => ((s.flag_codes || [])[k] === "sca_range" && scaRangeText(s)) || roundNumbers(f));
  resultBox.innerHTML = `
    <div class="answer" data-testid="solve-answer">${escapeHtml(answerHeadline(s))}</div>
    <p class="sentence" data-testid="answer-sentence">${escapeHtml(answerSentence(s))}</p>
    ${s.binding_limit ? `<div class="binding" data-testid="binding-limit">${escapeHtml(bindingText(s))}</div>` : ""}
    ${uncertaintyParts.length && !noConstraint ? `<div class="muted">uncertainty parts (1σ): ${uncertaintyParts.map(([k, v]) =>
      `${k} ${fmt(v * scale, 2)}${unit}`).join(" · ")}</div>` : ""}
    ${boundLines(s, noConstraint)}
    <div data-testid="slope-line">${escapeHtml(slopeText(s, methodRelativeOf(s)))}</div>
    <div data-testid="saturation-line">${escapeHtml(saturationText(s))}</div>
    ${s.shear ? `<div data-testid="shear">${escapeHtml(shearText(s.shear))}</div>` : ""}
    <div class="muted">applies to ${escapeHtml(s.applies_to)}</div>
    ${s.conditions.ramp ? `<div class="muted">slopes from ${escapeHtml(s.conditions.ramp_slopes_from)}</div>` : ""}
    ${flags.length ? flagsList(flags, s.flag_codes) : ""}
    <p class="scene-line" data-testid="scene-line">Scene: ${escapeHtml(sceneName(s))}
      ${sceneName(s) === PAPER_SCENE ? "" : '<button type="button" id="use-paper-scene">Use the paper\'s scene</button>'}</p>
    <p class="conditions">${escapeHtml(conditionsText({ ...s.conditions, band: s.band, sca: s.sca, exptime_s: s.exptime, beta0: s.beta0, fidelity: s.fidelity }))}
      · ${escapeHtml(MODE_NAME[s.mode] || s.mode)} · ${escapeHtml(METRIC_NAME[s.metric] || s.metric)}</p>`;
  resultBox.hidden = false;
  // The answer in one sentence at the top, so the first view says what it answers and for which scene.
  document.getElementById("top-answer").innerHTML = `<a href="#calc-title">Answer</a>: ${escapeHtml(answerSentence(s))}`;
  state.lastSolution = s;
  const paperButton = document.getElementById("use-paper-scene");
  if (paperButton) paperButton.addEventListener("click", usePaperScene);
}

// The solved quantity as the library gives it, in the headline's unit (no arithmetic here).
function solvedValueText(solved, v) {
  if (v === null || v === undefined || !Number.isFinite(v)) return "n/a";
  if (solved === "precision") return v >= 1 ? "no constraint" : `${fmt(v * 100, 3)} %`;
  if (solved === "magnitude") return `m = ${v.toFixed(2)}`;
  return `T = ${fmt(v, 3)}`;
}

// The answer's conservative bound and its ranges (what varies from star to star), as the library states them.
function boundLines(s, noConstraint) {
  const lines = [];
  const bound = s.conservative;
  if (bound && !noConstraint && bound[bound.solved_for] !== undefined) {
    lines.push(`<div class="muted" data-testid="conservative-line">conservative: ${escapeHtml(solvedValueText(bound.solved_for, bound[bound.solved_for]))} ` +
      `(slope bound |c| (1 + ${fmt(bound.relative_slope_bound, 2)}); ${escapeHtml(bound.coverage)})</div>`);
  }
  for (const [name, range] of Object.entries(s.ranges || {})) {
    const values = range[s.solved_for];
    if (!Array.isArray(values)) continue;
    const ends = (range.ends || []).map((e) => String(e).replace("blackbody:", "blackbody "));
    const label = name === "sed" ? "star colour (SED)" : name.replace(/_/g, " ");
    const at = values.map((v, k) => `${escapeHtml(solvedValueText(s.solved_for, v))}${ends[k] ? ` at ${escapeHtml(ends[k])}` : ""}`);
    lines.push(`<div class="muted" data-testid="range-line">${escapeHtml(label)}: ${at.join(" … ")} (${escapeHtml(range.why || "a range, not an uncertainty")})</div>`);
  }
  return lines.join("\n    ");
}

function bindingText(s) {
  const m = fmt(s.brightest_usable_magnitude, 4);
  if (isExtrapolated(s)) {
    return `no star the slopes reach meets T at this precision except by extrapolation: the NL error reaches T only at m = ${m}, ` +
      "fainter than the slopes are computed, by their flux law (see the note below); not a star the slopes hold";
  }
  return `brightest usable star m = ${m}: ${s.binding_limit === "saturation"
    ? "saturation binds (the brightest pixel reaches the full well before the NL error reaches T)"
    : "the nonlinearity binds (its error reaches T before the star saturates)"}`;
}

// "(2.31 ± 0.30) × 10⁻⁵" keeps its power of ten in the box: "2.31e-5".
function tolSuffix(s) {
  const text = withUncertainty(s.tolerance, s.uncertainty);
  const m = text.match(/× 10([⁻⁰¹²³⁴⁵⁶⁷⁸⁹]+)$/);
  if (!m) return "";
  const digits = { "⁻": "-", "⁰": 0, "¹": 1, "²": 2, "³": 3, "⁴": 4, "⁵": 5, "⁶": 6, "⁷": 7, "⁸": 8, "⁹": 9 };
  return `e${m[1].split("").map((ch) => digits[ch]).join("")}`;
}

function answerHeadline(s) {
  if (s.solved_for === "precision") {
    if (s.precision >= 1) return "precision p: no constraint (p ≥ 100 %)";
    return `precision p = ${percent(s.precision, s.uncertainty)}`;
  }
  if (s.solved_for === "magnitude") {
    const m = `magnitude m = ${magnitudeText(s.magnitude, s.uncertainty)}`;
    return isExtrapolated(s) ? `${m}, extrapolated beyond the faintest magnitude the slopes reach` : m;
  }
  return `tolerance T (${METRIC_LABEL[s.metric]}) = ${withUncertainty(s.tolerance, s.uncertainty)}`;
}

function sceneName(s) {
  const c = s.conditions || {};
  const named = c.scene_description || (typeof c.scene === "string" ? c.scene : c.scene && c.scene.description);
  if (!named || /^paper scene/.test(named)) return PAPER_SCENE;
  let text = roundNumbers(named);
  if (c.sca_range) {
    // Without a position the answer holds over the SCA: the node it reports is not the user's choice.
    text = text.replace(/,?\s*position [\d.]+\s*,\s*[\d.]+/, "").replace(/^(\w[\w-]*):\s*,?\s*/, "$1: anywhere on the SCA, ");
  }
  // The library names the default's scene "roman: position …, SED …": the page says it in words.
  if (/^roman:\s*/.test(text)) return `the Roman default scene (${text.replace(/^roman:\s*/, "")})`;
  return text;
}

// A short name of the answer's scene for the comparison table (the full one in its title).
function sceneShort(s) {
  const c = s.conditions || {};
  const name = sceneName(s);
  const base = name === PAPER_SCENE ? "the paper's" : /^the Roman default/.test(name) ? "Roman default" : (c.scene_name || "custom");
  const changed = c.roman_default_changed ? " (changed)" : "";
  const position = c.sca_range ? "whole SCA" : (name.match(/position ([\d.]+\s*,\s*[\d.]+)/) || [])[1];
  return `${base}${changed}${position ? `, ${position}` : ""}`;
}

// One sentence a requirement writer can paste: what must hold, for what, under which conditions.
function answerSentence(s) {
  const what = `${METRIC_LABEL[s.metric]}`;
  const stars = `${s.band} stars`;
  const where = `on SCA ${s.sca}, ${sceneName(s)}`;
  const beta = s.mode === "bias" ? "β" : "the pixel-to-pixel scatter of β";
  const known = s.mode === "bias" ? "known to" : "below";
  if (s.solved_for === "precision") {
    if (s.precision >= 1) {
      return `No constraint: ${what} stays within ${fmt(s.tolerance)} with ${stars} of m = ${fmt(s.magnitude)} ${where} ` +
        `even if ${beta} is off by its whole value (p ≥ 100 %).`;
    }
    const [value, error] = percent(s.precision, s.uncertainty).split(" ± ");
    return `${s.mode === "bias" ? "β must be known to" : `${beta} must stay below`} ${value}${error ? ` (± ${error})` : ""} ` +
      `for ${what} ≤ ${fmt(s.tolerance)} with ${stars} of m = ${fmt(s.magnitude)} ${where}.`;
  }
  if (s.solved_for === "tolerance") {
    return `With ${beta} ${known} ${fmt(100 * s.precision, 3)} %, ${stars} of m = ${fmt(s.magnitude)} ${where} keep ` +
      `${what} within ${withUncertainty(s.tolerance, s.uncertainty)}.`;
  }
  if (isExtrapolated(s)) {
    return `With ${beta} ${known} ${fmt(100 * s.precision, 3)} % and ${what} ≤ ${fmt(s.tolerance)}, every ${s.band} star the ` +
      `slopes reach ${where} exceeds the tolerance; by the slopes' flux law a star would meet it only at m = ${fmt(s.magnitude, 4)} ` +
      "(an extrapolation, not a star the slopes hold).";
  }
  return `With ${beta} ${known} ${fmt(100 * s.precision, 3)} % and ${what} ≤ ${fmt(s.tolerance)}, ${stars} ${where} ` +
    `can be used as bright as m = ${magnitudeText(s.magnitude, s.uncertainty)}${s.binding_limit ? ` (${s.binding_limit} sets the limit)` : ""}; ` +
    "brighter stars exceed the tolerance.";
}

function shearText(shear) {
  const kind = "m" in shear ? "m" : "c";
  const ratio = typeof shear.size_ratio === "number" ? fmt(shear.size_ratio)
    : `${shear.size_ratio.ratios.length} ratios, effective ${fmt(shear.size_ratio.effective)}`;
  if (shear.given === "tolerance") {
    return `implied shear bias |${kind}| = ${plusMinus(shear[kind], shear.uncertainty)} for a galaxy-to-PSF size ratio of ${ratio}`;
  }
  return `shear budget |${kind}| = ${fmt(shear[kind])} with a galaxy-to-PSF size ratio of ${ratio} → PSF tolerance T = ${fmt(shear.tolerance)}`;
}

// A refusal or a failure gives no answer to the question asked: the solved box is emptied and says
// why next to itself, an earlier answer stays greyed with what it answered (pin and downloads off),
// and the plots draw the refused question's curves where it has them, with no point and "no answer".
async function failAnswer(error, shortReason = null, body = null) {
  const form = document.getElementById("solve-form");
  const errorBox = document.getElementById("solve-error");
  const resultBox = document.getElementById("solve-result");
  const unknown = form.elements.solve_for.value;
  const solved = form.elements[unknown];
  solved.value = "";
  solved.placeholder = "no answer";
  solved.classList.add("failed");
  state.failed = true;
  let plain = plainWords(error.message);
  const field = error.field ? String(error.field).replace(/^scene\./, "") : null;
  let short = null;
  if (field === "magnitude" && /too bright|brighter than the tables|outside the tables|bright margin|saturates the brightest/.test(error.message) && body) {
    [plain, short] = await tooBright(body, error.message);
  } else if (error.unreachable) {
    plain = `${error.message}; retrying (see the note at the top of the page)`;
  }
  error.plain = error.errors && error.errors.length > 1 ? null : plain;
  showError(errorBox, form, error);
  const reason = shortReason || short || (error.unreachable ? "the server cannot be reached" : plain);
  if (field && ["precision", "tolerance", "magnitude"].includes(field)) setFieldMessage(field, plain);
  if (field !== unknown) setFieldMessage(unknown, field && field !== unknown ? `no answer: see ${fieldName(field)}` : `no answer: ${reason}`);
  if (state.lastSolution) {
    resultBox.hidden = false;
    setStale(`The question asked (${body ? questionText(body) : "the form's"}) has no answer: ${reason}`);
  } else {
    resultBox.hidden = true;
    setStale(null);
    for (const id of ["pin-answer", "download-json", "download-ecsv"]) document.getElementById(id).disabled = true;
  }
  document.getElementById("top-answer").textContent = state.lastSolution
    ? "No answer to the question asked: see the calculator below (the answer shown there, greyed, is for an earlier question)."
    : "No answer: see the calculator below.";
  // The refused question's own curves where it has them (a star too bright for them still has them);
  // no point, and a legend that reads nothing until hovered.
  let drawn = false;
  if (body && !error.unreachable && error.status === 422) {
    try {
      await drawAnswerPlots(body, null);
      drawn = true;
    } catch (_) {
      drawn = false;
    }
  }
  for (const name of ["req", "calc"]) {
    const plot = state.exports[name];
    const el = document.getElementById(`plot-${name}`);
    delete el.dataset.point;
    if (!drawn) {
      if (plot && error.unreachable) drawPlot(name, { ...plot, columns: plot.columns.filter((c) => !c.answer), cursorAt: null, noAnswer: true });
      else {
        // The refused question has no curves (e.g. a tolerance no star meets): none are left from another.
        if (state.plots[name]) state.plots[name].destroy();
        delete state.plots[name];
        delete state.exports[name];
        el.innerHTML = "";
        document.getElementById(`key-${name}`).innerHTML = "";
      }
    }
    setNoAnswer(name, reason);
  }
  // Curves drawn for the refused question are its own: not greyed.
  if (drawn) for (const figure of document.querySelectorAll("#calculator figure.plot")) figure.classList.remove("stale");
  document.getElementById("req-readout").textContent = "";
}

// The brightest magnitude the calculator answers for at the question's own conditions, from the server.
async function tooBright(body, original) {
  try {
    const limits = await api("/page/limits", { method: "POST", body: JSON.stringify(body) });
    if (limits.brightest_answered_magnitude === undefined) return [plainWords(original), null];
    const m = body.magnitude;
    const brightest = limits.brightest_answered_magnitude.toFixed(2);
    const readout = limits.readout === "ramp" ? "up the ramp, in the resultant a slope needs" : "in the final frame";
    return [`m = ${fmt(m)} is too bright: the brightest star answered at these conditions is m = ${brightest} (stars brighter ` +
      `than m = ${limits.saturation_magnitude.toFixed(2)} saturate ${readout}). Why: ${plainWords(original.replace(/^magnitude: /, ""))}.`,
    `m = ${fmt(m)} is too bright (brightest answered: m = ${brightest})`];
  } catch (_) {
    return [plainWords(original), null];
  }
}

function usePaperScene() {
  document.getElementById("solve-scene").value = "paper";
  exposurePlaceholder();
  const scene = document.getElementById("scene-form");
  scene.elements.preset.value = "";
  sceneFill("paper");
  document.getElementById("scene-use").checked = false;
  solve(null);
}

// ---- the calculator's plots, from api/v1/page/requirement -----------------------------------------

// The question's own curves (its scene, position, readout), each value the solver's; the answer's
// magnitude added to the grid so that its point is on them.
async function requirementData(body, solution) {
  const at = solution && Number.isFinite(solution.magnitude) ? [solution.magnitude] : [];
  const overlay = document.getElementById("calc-paper").checked;
  const data = await api(`/page/requirement?${query({ at, overlay: overlay ? "true" : null })}`, { method: "POST", body: JSON.stringify(body) });
  state.curves = data;
  return data;
}

async function drawAnswerPlots(body, solution) {
  const data = await requirementData(body, solution);
  drawRequirementPlot(data, solution);
  drawCalculatorPlot(data, solution);
  if (solution && methodRelativeOf(solution) === null) {
    const line = document.querySelector("[data-testid=slope-line]");
    if (line) line.textContent = slopeText(solution, data.curves.method_relative);
  }
}

// One saturation story: the limit that binds for this readout (shaded), the final frame's (a line, up
// the ramp), and, for the paper's quadratic on its tables' star, where it stops rising (hatched).
function limitShades(limits, from) {
  if (!limits || limits.saturation_magnitude === undefined) return [];
  const sat = limits.saturation_magnitude;
  const [low, high] = limits.saturation_range || [sat, sat];
  const where = high - low > 0.005 ? ` somewhere on the SCA (${low.toFixed(2)}–${high.toFixed(2)} over its positions)` : "";
  const readout = limits.readout === "ramp" ? "up the ramp (the resultant a slope needs)" : "in the final frame";
  const shades = [{ from, to: sat, label: `saturated ${readout}${where}: m < ${sat.toFixed(2)}; answers there are flagged`, color: "rgba(120,120,120,0.18)" }];
  if (limits.nonmonotonic_magnitude !== undefined && limits.nonmonotonic_magnitude > from) {
    shades.push({ from, to: limits.nonmonotonic_magnitude, label: `quadratic NL model invalid: 2β₀Q_peak ≥ 1 (m < ${limits.nonmonotonic_magnitude.toFixed(2)})`,
      color: "rgba(164,22,26,0.08)", hatch: "rgba(164,22,26,0.35)" });
  }
  return shades;
}

function limitMarkers(limits) {
  if (!limits || limits.readout !== "ramp" || limits.final_frame_saturation_magnitude === null || limits.final_frame_saturation_magnitude === undefined) return [];
  const [low, high] = limits.final_frame_saturation_range || [0, 0];
  const where = high - low > 0.005 ? ` (${low.toFixed(2)}–${high.toFixed(2)} over the SCA)` : "";
  return [{ x: limits.final_frame_saturation_magnitude, color: "#555",
    label: `final frame's limit${where}: brighter, the brightest pixel's last resultants saturate and are dropped from the fit` }];
}

// The curves' scene, position and readout in words (captions, titles).
function curveWords(data) {
  const c = data.curves.conditions || {};
  const scene = c.scene_description ? sceneName({ conditions: { scene_description: c.scene_description } }) : PAPER_SCENE;
  const readout = c.ramp ? `up the ramp: ${c.ramp.description}` : "a single final frame";
  return `${scene}; ${data.curves.where.words}; ${readout}`;
}

function captionNotes(data, overlayShown) {
  const c = data.curves;
  const notes = [];
  if (c.needs_simulation) notes.push(`No curve: ${plainWords(c.needs_simulation)}. The point is the answer.`);
  else notes.push(`The curves are the answer's own scene and readout — ${curveWords(data)} — each value the solver's own answer at that magnitude, so the answer's point lies on its curve.`);
  if (c.gaps) notes.push(`Gaps: ${plainWords(c.gaps)}.`);
  if (c.extrapolated_from !== null && c.extrapolated_from !== undefined) notes.push(`Fainter than m = ${fmt(c.extrapolated_from)} the slopes follow their flux law (extrapolated).`);
  if (overlayShown && data.paper) notes.push("Grey, dashed: the paper's idealised scene (the shipped tables, a single final frame) at the same band, detector, exposure, β₀ and full well.");
  if (overlayShown && data.published) notes.push("Open circles: the paper's published values (Plazas et al. 2016, Cycle-5 optics).");
  return notes.join(" ");
}

function pct(v) {
  // p in percent for the plot; above 100 % (or inf) there is no constraint: not drawn.
  if (v === null || v === undefined || v === "inf") return null;
  return v < 1 ? 100 * v : null;
}

function drawRequirementPlot(data, solution) {
  const c = data.curves;
  const conditions = c.conditions || {};
  const band = conditions.band || (solution && solution.band);
  const metric = conditions.metric || (solution && solution.metric);
  const mode = conditions.mode || (solution && solution.mode);
  const color = BAND_COLORS[band] || "#333";
  const bias = mode === "bias";
  const dashes = { 0.1: [2, 3], 0.3333333333333333: [8, 4], 3: [12, 3, 2, 3], 10: [4, 4] };
  const columns = c.requirement.map((r) => {
    const chosen = r.factor === 1;
    const label = `T = ${fmt(r.tolerance, 3)}${chosen ? " (chosen)" : ""}`;
    const y = r.precision.map(pct);
    const err = r.statistical.map((e, i) => (e == null || y[i] == null ? null : 100 * e));
    // Only the chosen T carries its uncertainty band (the others would be a thicket of whiskers).
    return { label, tag: `T = ${fmt(r.tolerance, 2)}`, tagAt: "start", x: c.magnitude, y, err: chosen ? err : null,
      fid: chosen ? c.method_relative : null, band: chosen ? true : undefined,
      series: { ...lineSeries(label, chosen ? color : shade(color, r.factor), chosen ? undefined : dashes[r.factor] || [4, 4], chosen ? 3 : 1.4) } };
  }).filter((col) => col.label && col.x.length);
  const overlay = document.getElementById("calc-paper").checked;
  if (overlay && data.paper && data.paper.requirement) {
    const r = data.paper.requirement.find((x) => x.factor === 1);
    if (r) {
      const label = `the paper's idealised scene, T = ${fmt(r.tolerance, 3)}`;
      columns.push({ label, tag: "paper's scene", tagAt: "start", x: data.paper.magnitude, y: r.precision.map(pct), band: false,
        series: lineSeries(label, "#595959", [7, 4], 1.6) });
    }
  }
  if (overlay && data.published && data.published.precision) {
    const label = "Plazas et al. 2016, published (Cycle-5 optics)";
    columns.push({ label, x: data.published.magnitude, y: data.published.precision.map(pct), band: false,
      series: openPointSeries(label, "#1d2330", 9) });
  }
  const magnitudes = c.magnitude.filter((m) => m !== null);
  const from = (magnitudes.length ? Math.min(...magnitudes) : (solution ? solution.magnitude : 15)) - 0.5;
  const shades = limitShades(c.limits, from);
  const noConstraint = solution && solution.precision >= 1;
  if (solution && !noConstraint) {
    const label = solution.binding_limit === "saturation"
      ? `answer: saturation binds at m = ${fmt(solution.magnitude)} (p = ${fmt(100 * solution.precision, 3)} %: the NL error there is below T)`
      : `answer: m = ${fmt(solution.magnitude)}, p = ${fmt(100 * solution.precision, 3)} %`;
    columns.push({ label, answer: true, band: false, x: [solution.magnitude], y: [100 * solution.precision], series: pointSeries("answer", "#c00000", 12) });
  }
  const stars = conditions.stars || (solution && solution.stars) || 1;
  const averaging = mode === "scatter" && stars > 1 ? ` (averaged over ${stars} stars)` : "";
  document.getElementById("req-scene-note").textContent = captionNotes(data, overlay);
  drawPlot("req", {
    title: `Required ${bias ? "Δβ/β₀" : "σβ/β₀"} vs magnitude for ${METRIC_LABEL[metric]} tolerances around T = ${fmt(c.tolerance)}${averaging}\n` +
      `${curveWords(data)}\n${conditionsText({ ...conditions, exptime_s: conditions.exptime, full_well_e: conditions.full_well })}`,
    xLabel: "magnitude (AB)",
    yLabel: `precision p = ${bias ? "Δβ/β₀" : "σβ/β₀"} [%]`,
    logY: true,
    columns,
    shades,
    markers: limitMarkers(c.limits),
    cursorAt: solution ? solution.magnitude : null,
    noAnswer: !solution,
  });
  const el = document.getElementById("plot-req");
  if (solution) el.dataset.point = `${solution.magnitude},${solution.precision}`;
  el.dataset.answer = !solution ? "none" : noConstraint ? "no-constraint" : "shown";
  setNoAnswer("req", solution && noConstraint ? "no constraint: p ≥ 100 % at the answer" : null);
  if (c.needs_simulation && solution) setNoAnswer("req", "no curve at table cost for this question (see below): the point is the answer", "");
  const u = state.plots.req;
  const readout = document.getElementById("req-readout");
  readout.textContent = "";
  if (!u || !solution) return;
  const chosen = state.exports.req.columns.find((col) => col.label.endsWith("(chosen)"));
  const show = (i) => {
    if (i == null) i = u.defaultIdx;
    const m = u.data[0][i];
    if (!chosen) return;
    const j = chosen.x.indexOf(m);
    if (j < 0 || chosen.y[j] == null) return;
    const p = chosen.y[j];
    const stat = chosen.err[j];
    const fidelity = chosen.fid != null ? p * chosen.fid : null;
    const where = m < c.limits.saturation_magnitude ? " — saturated for this readout" : "";
    readout.textContent = `m = ${fmt(m, 4)}: p ≤ ${withUncertainty(p, fidelity != null ? Math.hypot(stat || 0, fidelity) : stat, "%")} ` +
      `(statistical ± ${fmt(stat, 2)} %${fidelity != null ? `, method ± ${fmt(fidelity, 2)} %` : ""}) keeps ${METRIC_LABEL[metric]} within T = ${fmt(c.tolerance, 3)}${where}`;
    readout.dataset.magnitude = String(m);
    readout.dataset.precision = String(p / 100);
  };
  u.hooks.setCursor = [(plot) => show(plot.cursor.idx)];
  show(null);
}

function shade(hex, factor) {
  const n = parseInt(hex.slice(1), 16);
  const mix = factor < 1 ? 255 : 0;
  const w = Math.min(0.6, 0.25 * Math.abs(Math.log10(factor)) + 0.2);
  const channel = (shift) => Math.round(((n >> shift) & 255) * (1 - w) + mix * w);
  return `rgb(${channel(16)},${channel(8)},${channel(0)})`;
}

function drawCalculatorPlot(data, solution) {
  const c = data.curves;
  const conditions = c.conditions || {};
  const band = conditions.band || (solution && solution.band);
  const metric = conditions.metric || (solution && solution.metric);
  const mode = conditions.mode || (solution && solution.mode);
  const label = `${band} ${mode === "bias" ? "bias" : "scatter"} slope${c.signed ? " (|c|)" : ""}`;
  const columns = [
    { label, tag: band, x: c.magnitude, y: c.slope_abs, err: c.slope_statistical, fid: c.method_relative,
      series: lineSeries(label, BAND_COLORS[band] || "#333", BAND_DASH[band]) },
  ];
  const overlay = document.getElementById("calc-paper").checked;
  if (overlay && data.paper) {
    const paperLabel = "the paper's idealised scene (tables, final frame)";
    columns.push({ label: paperLabel, tag: "paper's scene", x: data.paper.magnitude, y: data.paper.slope_abs, band: false,
      series: lineSeries(paperLabel, "#595959", [7, 4], 1.6) });
  }
  if (overlay && data.published) {
    const pubLabel = "Plazas et al. 2016, published (Cycle-5 optics)";
    columns.push({ label: pubLabel, x: data.published.magnitude, y: data.published.slope.map(Math.abs), band: false,
      series: openPointSeries(pubLabel, "#1d2330", 9) });
  }
  if (solution && solution.slope !== null && solution.slope !== undefined) {
    columns.push({ label: `answer: m = ${fmt(solution.magnitude)}, c = ${fmt(solution.slope)}`, x: [solution.magnitude],
      y: [Math.abs(solution.slope)], answer: true, band: false, series: pointSeries("answer", "#c00000", 12) });
  }
  const magnitudes = c.magnitude.filter((m) => m !== null);
  const from = (magnitudes.length ? Math.min(...magnitudes) : (solution ? solution.magnitude : 15)) - 0.5;
  document.getElementById("calc-scene-note").textContent = captionNotes(data, overlay);
  drawPlot("calc", {
    markers: limitMarkers(c.limits),
    shades: limitShades(c.limits, from),
    cursorAt: solution ? solution.magnitude : null,
    noAnswer: !solution,
    title: `${label} vs magnitude${solution ? "; answer marked" : ""}\n${curveWords(data)}\n` +
      `${conditionsText({ ...conditions, exptime_s: conditions.exptime, full_well_e: conditions.full_well })}`,
    xLabel: "magnitude (AB)",
    yLabel: `${mode === "bias" ? "d" : "σ"}(${METRIC_LABEL[metric]})/${mode === "bias" ? "dβ" : "σβ"} [e⁻]`,
    logY: true,
    columns,
  });
  const el = document.getElementById("plot-calc");
  if (solution) el.dataset.point = `${solution.magnitude},${solution.slope}`;
  el.dataset.answer = solution ? "shown" : "none";
  setNoAnswer("calc", c.needs_simulation && solution ? "no curve at table cost for this question (see below): the point is the answer" : null, "");
}

// ---- curves -----------------------------------------------------------------------------------

function paperOn() {
  return document.getElementById("paper-overlay").checked && state.paper;
}

// The words of every band's slopes: the question's band's, and where a band's own differ (each band
// has its own sky background and, without a position, its own count of field-grid nodes), each band's
// own values, so that no band's numbers are stated for all.
function slopesWords(curves, own) {
  const wordsOf = (c) => curveWords({ curves: { conditions: c.conditions, where: c.where } });
  const words = wordsOf(own);
  if (curves.every((c) => wordsOf(c) === words)) return words;
  const BACKGROUND = /background [^,;)]* e-/;
  const background = (c) => (c.conditions.scene && c.conditions.scene.background_e) || 0;
  const nodes = (c) => (c.where.kind === "envelope" ? c.where.positions.length : 1);
  const byBackground = curves.some((c) => background(c) !== background(own));
  const byNodes = curves.some((c) => nodes(c) !== nodes(own));
  // A band whose words are the question's band's but for those two values is said by them; any
  // other difference, in its own words.
  const asOwn = (c) => {
    const described = (c.conditions.scene_description || "").replace(BACKGROUND, ((own.conditions.scene_description || "").match(BACKGROUND) || [""])[0]);
    return wordsOf({ conditions: { ...c.conditions, scene_description: described }, where: own.where }) === words;
  };
  const each = curves.map((c) => {
    if (!asOwn(c)) return `${c.band}: ${wordsOf(c)}`;
    const values = [];
    if (byBackground) values.push(`background ${fmt(background(c), 3)} e⁻`);
    if (byNodes) values.push(nodes(c) === 1 ? "one position" : `${nodes(c)} nodes`);
    return `${c.band} ${values.join(", ")}`;
  });
  return `${words} (as stated for ${own.band}; each band at its own — ${each.join("; ")})`;
}

// Every band's slope for the calculator's question (the answer's, once there is one).
async function drawSlopes() {
  const metric = document.getElementById("slopes-metric").value;
  const mode = document.getElementById("slopes-mode").value;
  const at = state.lastSolution && state.current !== false ? state.lastSolution.magnitude : 18.3;
  const question = state.lastRequest || questionBody().body;
  const body = { ...question, metric, mode, ...(mode === "bias" ? { stars: 1 } : {}) };
  state.slopesAt = at;
  const data = await api(`/page/slopes?${query({ at })}`, { method: "POST", body: JSON.stringify(body) });
  const columns = data.curves.map((curve) => ({
    label: curve.band,
    tag: curve.band,
    x: curve.magnitude,
    y: curve.slope,
    err: curve.statistical,
    fid: curve.fidelity_relative_uncertainty,
    series: lineSeries(curve.band, BAND_COLORS[curve.band] || "#333", BAND_DASH[curve.band]),
  }));
  const paper = paperOn();
  if (paper && metric !== "e") {
    const figure = mode === "bias" ? paper.fig3_bias_slopes_per_beta : paper.fig5_scatter_slopes_per_sigma_beta;
    for (const [band, values] of Object.entries(figure)) {
      columns.push({ label: `${band} (paper)`, x: paper.magnitudes, y: values[metric].map((v) => Math.abs(v)),
        series: pointSeries(`${band} (paper)`, BAND_COLORS[band] || "#333", 7) });
    }
  }
  const own = data.curves.find((c) => c.band === question.band) || data.curves[0];
  const words = slopesWords(data.curves, own);
  const missing = data.curves.filter((c) => c.needs_simulation).map((c) => c.band);
  const title = `${mode} slope of ${METRIC_LABEL[metric]} vs magnitude (absolute values), every band\n${words}\n` +
    conditionsText({ ...own.conditions, band: "all bands", exptime_s: own.conditions.exptime, full_well_e: own.conditions.full_well });
  document.getElementById("curves-scene-text").textContent = `The slopes of every band are for the ${state.lastRequest ? "answer's" : "calculator's"} ` +
    `question: ${words}.`;
  document.getElementById("slopes-caption").textContent =
    `Scene: ${title.split("\n").slice(1).join(". ")}. Lines: each band with its own dash and its name at the faint end, from the brightest ` +
    `magnitude the calculator answers; legend values at m = ${fmt(at)}${state.lastSolution ? " (the answer's magnitude)" : ""}. ` +
    "Points: the paper (Cycle-5 optics, its idealised scene), when shown." + (paper && metric === "e" ? " The paper has no |Δe| data." : "") +
    (missing.length ? ` No curve at table cost for ${missing.join(", ")}: ${plainWords(data.curves.find((c) => c.needs_simulation).needs_simulation)}.` : "");
  drawPlot("slopes", {
    title,
    xLabel: "magnitude (AB)",
    yLabel: `${mode === "bias" ? "d" : "σ"}(${METRIC_LABEL[metric]})/${mode === "bias" ? "dβ" : "σβ"} [e⁻]`,
    logY: true,
    columns,
    cursorAt: at,
  });
}

function simulationPoints(kind, band, metric, magnitude) {
  const sim = state.lastSimulation;
  if (!sim || metric === "e") return [];
  const key = METRIC_KEY[metric];
  const rows = sim.results.filter((r) => r.band === band && Math.abs(r.magnitude - magnitude) < 1e-9 &&
    (kind === "beta" ? r.sigma_beta === 0 : r.sigma_beta > 0));
  if (rows.length === 0) return [];
  // Error bars from the API: the standard error of the mean, and of a spread its std_error (a result
  // stored before std_error existed draws its point without a bar).
  const point = (r) => (kind === "beta"
    ? [r.beta, r[key].mean, r[key].stderr]
    : [r.sigma_beta, r[key].std, r[key].std_error ?? null]);
  const groups = new Map();
  for (const r of rows) {
    const group = kind === "beta" ? `σβ = ${fmt(r.sigma_beta)}` : `β = ${fmt(r.beta)}`;
    if (!groups.has(group)) groups.set(group, []);
    groups.get(group).push(point(r));
  }
  const several = groups.size > 1;
  return [...groups.entries()].map(([group, points], k) => {
    const label = `fresh simulation${kind === "sigma" || several ? `, ${group}` : ""} (${fidelityName(sim.fidelity)}, ${rows[0].realizations} realizations)`;
    return { label, x: points.map((p) => p[0]), y: points.map((p) => p[1]), err: points.map((p) => p[2]), band: false,
      series: pointSeries(label, SERIES_COLORS[k % SERIES_COLORS.length], 9) };
  });
}

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

// Fresh points drawn on a table line of the paper's idealised scene come from the simulation's own
// scene and readout (the Roman default unless the scene box is ticked): said, so that points off the
// line are not read as a disagreement of the same question.
function freshSceneNote(drawn) {
  const sim = state.lastSimulation;
  if (!sim || drawn.length === 0) return "";
  const c = sim.conditions || {};
  const scene = sceneName(sim);
  const readout = c.ramp ? `up the ramp (${c.ramp.description})` : "a single final frame";
  const exposure = c.exptime_s != null ? `, ${fmt(c.exptime_s)} s` : "";
  if (scene === PAPER_SCENE && !c.ramp) return "";
  return ` The points are the simulation's own question (scene: ${scene}; ${readout}${exposure}), not the line's (the paper's ` +
    "idealised scene): they need not lie on it.";
}

function flagsText(flags) {
  return flags.length ? ` Notes: ${flags.map(plainWords).join("; ")}` : "";
}

async function drawBeta() {
  const c = sharedConditions();
  const band = document.getElementById("beta-band").value;
  const metric = document.getElementById("beta-metric").value;
  const magnitude = document.getElementById("beta-magnitude").value.trim();
  const log = document.getElementById("beta-log").checked;
  const data = await api(`/curves/beta?${query({ band, metric, magnitude, ...c })}`);
  const label = `${band}, m = ${fmt(data.magnitude)} (table, first order)`;
  const columns = [{ label, tag: band, x: data.beta, y: data.values, err: data.uncertainty, fid: data.fidelity_relative_uncertainty,
    series: lineSeries(label, BAND_COLORS[band] || "#333", BAND_DASH[band]) }];
  const paper = paperOn();
  if (paper && metric !== "e" && paper["fig2_at_m18.3"][band]) {
    const fig = paper["fig2_at_m18.3"][band];
    columns.push({ label: `${band} paper, m = 18.3`, x: fig.beta, y: fig[METRIC_KEY[metric]],
      series: pointSeries(`${band} paper, m = 18.3`, "#555", 7) });
  }
  const fresh = simulationPoints("beta", band, metric, Number(magnitude));
  columns.push(...fresh);
  if (log) {
    for (const column of columns) column.y = column.y.map((v) => (v === null ? null : Math.abs(v)));
  }
  const title = `${METRIC_LABEL[metric]} vs β at m = ${fmt(data.magnitude)}: the paper's idealised scene (shipped tables, first order)\n${conditionsText(data.conditions)}`;
  document.getElementById("beta-caption").textContent = `The paper's idealised scene: its tables, to first order in β. ${conditionsText(data.conditions)}. ` +
    `Slope c = ${fmt(data.slope)} per unit β (relative uncertainty: statistical ${fmt(data.uncertainty.at(-1) / Math.abs(data.values.at(-1)), 2)}` +
    `${data.fidelity_relative_uncertainty != null ? `, method ${fmt(data.fidelity_relative_uncertainty, 2)}` : ""}). ` +
    "A fresh simulation with several β gives the full, nonlinear response." + flagsText(data.flags) + freshSceneNote(fresh);
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
  const columns = [{ label, tag: band, x: data.sigma_beta, y: data.values, err: data.uncertainty, fid: data.fidelity_relative_uncertainty,
    series: lineSeries(label, BAND_COLORS[band] || "#333", BAND_DASH[band]) }];
  const fresh = simulationPoints("sigma", band, metric, Number(magnitude));
  columns.push(...fresh);
  const title = `σ(${METRIC_LABEL[metric]}) vs σβ at m = ${fmt(data.magnitude)}: the paper's idealised scene (shipped tables, first order)\n${conditionsText(data.conditions)}`;
  document.getElementById("sigma-caption").textContent = `The paper's idealised scene: its tables, to first order in σβ. ${conditionsText(data.conditions)}. ` +
    `Scatter slope = ${fmt(data.slope)} per unit σβ. A fresh simulation with σβ values gives Monte Carlo points.` +
    flagsText(data.flags) + freshNote(fresh, band, Number(magnitude), metric) + freshSceneNote(fresh);
  drawPlot("sigma", { title, xLabel: "σβ [1/e⁻]", yLabel: `σ(${METRIC_LABEL[metric]})`, columns, logX: log, logY: log });
}

async function drawCurves() {
  const box = document.getElementById("curves-error");
  clearError(box, null);
  const results = await Promise.allSettled([drawSlopes(), drawBeta(), drawSigma()]);
  const failed = results.find((r) => r.status === "rejected");
  if (failed) {
    showError(box, null, failed.reason);
    if (failed.reason.unreachable) connection.lost("curves", () => drawCurves());
  }
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
    ...(form.elements.exptime.value.trim() ? { exptime: numberOrText(form.elements.exptime.value) } : {}),
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
  const wavelengths = form.elements.n_wavelengths.value.trim();
  if (wavelengths) body.scene = { ...(body.scene || { preset: "roman" }), n_wavelengths: numberOrText(wavelengths) };
  setProgress(0, "submitting");
  try {
    const job = await api("/simulations", { method: "POST", body: JSON.stringify(body) });
    followJob(job);
  } catch (error) {
    const limit = state.meta && state.meta.limits && state.meta.limits.max_wavelengths;
    if (!wavelengths && limit && error.status === 422 && /max_wavelengths/.test(error.message)) {
      // The star's colour asks for more wavelengths than this server allows: run at the limit, and say so.
      const asked = (error.message.match(/asks for (\d+) wavelengths/) || [])[1];
      form.elements.n_wavelengths.value = String(limit);
      document.getElementById("hint-sim-wavelengths").textContent = `${body.band}'s star colour asks for ${asked || "more"} wavelengths ` +
        `for 0.1 % of the slopes; this server allows ${limit}, so the simulation runs with ${limit} (a coarser wavelength sampling; ` +
        "clear the field to ask for the automatic choice again).";
      return runSimulation(new Event("submit"));
    }
    setProgress(0, error.unreachable ? "not started: the server cannot be reached" : "not started");
    showError(errorBox, form, error);
  }
}

function setProgress(fraction, message) {
  document.getElementById("sim-progress").value = fraction;
  document.getElementById("sim-progress-text").textContent = `${Math.round(fraction * 100)}% — ${message}`;
}

// Follows a simulation to its end. The job's id is kept in this tab's session storage, so a reload,
// a lost connection or a restarted server picks the same job up again and shows how it really ended.
function followJob(job) {
  const cancel = document.getElementById("sim-cancel");
  const submit = document.getElementById("sim-button");
  if (state.polling) clearTimeout(state.polling);
  sessionStorage.setItem("nlpsf-job", job.id);
  const poll = async () => {
    try {
      step(await api(`/simulations/${job.id}`));
    } catch (error) {
      if (error.unreachable) {
        setProgress(document.getElementById("sim-progress").value, "the server cannot be reached; following the job again when it answers");
        connection.lost("job", poll);
        return;
      }
      sessionStorage.removeItem("nlpsf-job");
      showError(document.getElementById("sim-error"), null, error);
      cancel.disabled = true;
      submit.disabled = false;
    }
  };
  const step = (current) => {
    setProgress(current.progress, current.cached ? "answered from stored results" : progressText(current).replace(/^\d+ % done · /, ""));
    const sim = document.getElementById("sim-progress-text");
    sim.dataset.status = current.status;
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
      state.polling = setTimeout(poll, 250);
      return;
    }
    sessionStorage.removeItem("nlpsf-job");
    cancel.disabled = true;
    submit.disabled = false;
    if (current.status === "done") {
      setProgress(1, current.cached ? "done (answered from stored results)" : "done");
      showSimulation(current.result);
    } else {
      setProgress(current.progress || 0, `${current.status}: ${current.message || ""}`);
      showError(document.getElementById("sim-error"), null, new ApiError(jobEnding(current)));
    }
  };
  step(job);
}

function showSimulation(result) {
  state.lastSimulation = result;
  const box = document.getElementById("sim-result");
  document.getElementById("sim-conditions").textContent = `${result.source}. ${conditionsText(result.conditions)}`;
  const head = ["m", "β", "σβ", "flux [e⁻]", "peak [e⁻]", "ΔR/R", "Δe₁", "Δe₂", "σ(ΔR/R)", "notes"];
  const table = document.getElementById("sim-table");
  table.tHead.innerHTML = `<tr>${head.map((h) => `<th scope="col">${escapeHtml(h)}</th>`).join("")}</tr>`;
  table.tBodies[0].innerHTML = result.results.map((r) => `<tr>
      <td>${fmt(r.magnitude)}</td><td>${fmt(r.beta)}</td><td>${fmt(r.sigma_beta)}</td>
      <td>${fmt(r.flux_electrons)}</td><td>${fmt(r.peak_electrons)}</td>
      <td>${plusMinus(r.dR_over_R.mean, r.dR_over_R.stderr)}</td><td>${plusMinus(r.de1.mean, r.de1.stderr)}</td>
      <td>${plusMinus(r.de2.mean, r.de2.stderr)}</td><td>${fmt(r.dR_over_R.std)}</td>
      <td class="flags-cell">${escapeHtml(r.flags.map(plainWords).join("; "))}</td></tr>`).join("");
  box.hidden = false;
  markScrollable(table.parentElement);
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
  const first = result.results[0] || {};
  downloadText(`nlpsf-simulation-${first.band || ""}-sca${first.sca || ""}-${result.fidelity || ""}.csv`, lines.join("\n") + "\n", "text/csv");
}

// ---- scene and impact ------------------------------------------------------------------------

function sceneBody() {
  const f = document.getElementById("scene-form").elements;
  const scene = {};
  const text = (name) => f[name].value.trim();
  const given = (name) => text(name) !== "" && text(name).toLowerCase() !== "none" && text(name).toLowerCase() !== "off";
  // The base is always named: a scene without one is the Roman default's to the API.
  scene.preset = f.preset.value || "paper";
  // The position is the calculator's (one field for the answer, the impact and fresh simulations).
  const position = document.getElementById("solve-position").value.trim();
  if (position) scene.position = listOf(position);
  if (given("sed")) scene.sed = text("sed");
  for (const name of ["jitter", "charge_diffusion", "bfe", "background"]) {
    if (given(name)) scene[name] = numberOrText(text(name));
  }
  if (given("ipc")) scene.ipc = numberOrText(text("ipc"));
  if (f.ipc_order.value) scene.ipc_order = f.ipc_order.value;
  if (given("nl_coefficients")) scene.nl_coefficients = listOf(text("nl_coefficients"));
  return Object.keys(scene).length ? scene : null;
}

// The library's preset values in the form's fields, so that what the preset does is visible.
function sceneFill(name) {
  const preset = state.presets && state.presets.scenes[name || "paper"];
  if (!preset) return;
  const f = document.getElementById("scene-form").elements;
  for (const [field, value] of Object.entries(preset.fields)) f[field].value = value === "" ? "" : String(value);
  // A background left blank is the preset's own sky where it has one (the Roman default's), else none.
  f.background.placeholder = preset.sky ? "the preset's sky over the exposure" : "off";
}

function sceneError(error) {
  const field = error.field && error.field.startsWith("scene.") ? error.field.slice(6) : error.field;
  return new ApiError(error.message, field, error.status, error.errors, { unreachable: error.unreachable });
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
    // Empty: the impact report's own exposure (the paper's final frame, as its scene's base).
    ...(s.exptime.value.trim() ? { exptime: numberOrText(s.exptime.value) } : {}),
    magnitude: (state.lastSolution && state.lastSolution.magnitude) ?? numberOrText(s.magnitude.value) ?? 18.3,
    realizations: 30,
  };
  const scene = sceneBody();
  if (scene) body.scene = scene;
  button.disabled = true;
  button.textContent = "Measuring…";
  stateToUrl();
  try {
    await showImpact(await api("/impact", { method: "POST", body: JSON.stringify(body), followJob: true }));
  } catch (error) {
    if (error.unreachable) connection.lost("impact", () => measureImpact(null));
    showError(box, form, sceneError(error));
  } finally {
    button.disabled = false;
    button.textContent = "Measure impact";
  }
}

// Each effect in requirement terms: what it does to the precision the answer asks for.
async function showImpact(report) {
  const c = report.conditions;
  const metric = c.metric;
  const values = report.effects.map((e) => e.impact[metric]);
  const solution = state.lastSolution;
  const p = solution && solution.precision > 0 ? solution.precision : null;
  let shifted = [];
  if (p) {
    const usable = values.map((v) => (v === null ? 0 : v));
    shifted = (await api(`/page/impact-terms?${query({ precision: p, impact: usable })}`)).precision;
  }
  const modelled = new Set(((solution && solution.model && solution.model.included) || []).map((e) => e.name || e));
  const largest = Math.max(1e-12, ...values.filter((v) => v !== null).map(Math.abs));
  document.getElementById("impact-summary").textContent = p
    ? `What each effect does to the answer's precision p = ${fmt(100 * p, 3)} % (${METRIC_LABEL[metric]} ≤ ${fmt(solution.tolerance)}, ` +
      `${c.band}, m = ${fmt(c.magnitude)}): a stronger response asks a finer calibration.`
    : "Solve first to see what each effect does to the precision; here: the change of the slope.";
  document.getElementById("impact-conditions").textContent =
    `${c.band} · detector ${c.sca} · m = ${fmt(c.magnitude)} · β₀ = ${fmt(c.beta0)} /e⁻ · ${METRIC_NAME[metric] || metric}, ${MODE_NAME[c.mode] || c.mode} · ` +
    `scene: ${c.scene_description} · impact = slope with the effect ÷ without − 1 (linear response, ${c.realizations} random centroids)`;
  document.getElementById("impact-bars").innerHTML = report.effects
    .map((e, k) => {
      const v = values[k];
      const [plain, about] = effectWords(e.name);
      const width = v === null ? 0 : (50 * Math.abs(v)) / largest;
      const side = v !== null && v < 0 ? "neg" : "pos";
      const change = v === null ? "" : `slope ${v > 0 ? "+" : ""}${fmt(100 * v, 3)} %`;
      const inAnswer = modelled.has(e.name) ? "in the answer" : e.on ? "on in this scene" : "not in the answer";
      const label = v === null
        ? `not measured: ${plainNote(e.note || "no value given")}`
        : p ? `p ${fmt(100 * p, 3)} % → ${fmt(100 * shifted[k], 3)} % (${change})` : change;
      return `<div class="bar-row" data-effect="${escapeHtml(e.name)}">` +
        `<span class="bar-name">${escapeHtml(plain)}${e.on ? " (on)" : ""}<span class="muted small"> · ${escapeHtml(inAnswer)}</span></span>` +
        `<span class="bar-track" aria-hidden="true"><span class="bar ${side}" style="width:${width}%"></span></span>` +
        `<span class="bar-value">${escapeHtml(label)}</span>` +
        `<span class="bar-about muted">${escapeHtml(about)}${e.note && v !== null ? ` (${escapeHtml(plainNote(e.note))})` : ""}</span></div>`;
    })
    .join("");
  document.getElementById("impact-result").hidden = false;
}

// "measured at galsim.roman.ipc_kernel" in a reader's words.
function plainNote(note) {
  return plainWords(String(note).replace(/galsim\.roman\.\w+/g, "GalSim's Roman value"));
}

function fillExplanations() {
  const dl = (entries) => entries.map(([k, [name, about]]) => `<dt>${escapeHtml(name)}</dt><dd>${escapeHtml(about)}</dd>`).join("");
  const effects = ((state.meta && state.meta.scene_effects) || []).map((e) => [e.name, effectExplanation(e)]);
  document.getElementById("effect-explanations").innerHTML = dl([...effects, ["pupil_scale", PUPIL_SCALE_WORDS]]);
  document.getElementById("fidelity-explanations").innerHTML = dl(Object.entries(FIDELITIES));
}

// ---- comparison table --------------------------------------------------------------------------

// The answer first (it must never scroll away), the scene in a few words (the whole of it in the cell's title).
const COMPARE_COLUMNS = [
  ["answer", (s) => answerHeadline(s).replace(/^(precision|tolerance|magnitude) /, "")], ["band", (s) => s.band], ["detector", (s) => s.sca], ["PSF quantity", (s) => METRIC_LABEL[s.metric]],
  ["kind", (s) => s.mode], ["given", (s) => givenText(s)], ["scene", (s) => sceneShort(s), (s) => sceneName(s)],
  ["method", (s) => fidelityName(s.fidelity)], ["exposure [s]", (s) => fmt(s.exptime)], ["β₀ [1/e⁻]", (s) => fmt(s.beta0)],
];

function givenText(s) {
  const given = [];
  if (s.solved_for !== "precision") given.push(`p = ${fmt(100 * s.precision, 4)} %`);
  if (s.solved_for !== "tolerance") given.push(s.shear && s.shear.given !== "tolerance" ? shearText(s.shear) : `T = ${fmt(s.tolerance)}`);
  if (s.solved_for !== "magnitude") given.push(`m = ${fmt(s.magnitude)}`);
  return given.join(", ");
}

function pinAnswer() {
  if (!state.lastSolution || !state.current) return;
  state.pinned.push(state.lastSolution);
  renderComparison();
}

// The pinned answers survive a reload (this browser's local storage; the link carries the inputs).
function savePinned() {
  try {
    localStorage.setItem("nlpsf-pinned", JSON.stringify(state.pinned));
  } catch (_) {
    // storage full or disabled: the table still works for this page load
  }
}

function loadPinned() {
  try {
    const saved = JSON.parse(localStorage.getItem("nlpsf-pinned") || "[]");
    state.pinned = Array.isArray(saved) ? saved.filter((s) => s && s.band && s.solved_for) : [];
  } catch (_) {
    state.pinned = [];
  }
  renderComparison();
}

function renderComparison() {
  savePinned();
  const section = document.getElementById("comparison");
  section.hidden = state.pinned.length === 0;
  const table = document.getElementById("compare-table");
  table.tHead.innerHTML = `<tr><th scope="col">#</th>${COMPARE_COLUMNS.map(([h]) => `<th scope="col">${escapeHtml(h)}</th>`).join("")}<th scope="col"><span class="visually-hidden">remove</span></th></tr>`;
  table.tBodies[0].innerHTML = state.pinned.map((s, i) => `<tr><th scope="row">${i + 1}</th>${COMPARE_COLUMNS.map(([h, f, title]) =>
    `<td data-column="${escapeHtml(h)}"${title ? ` title="${escapeHtml(title(s))}"` : ""}>${escapeHtml(f(s))}</td>`).join("")}<td><button type="button" data-unpin="${i}" aria-label="remove row ${i + 1}">✕</button></td></tr>`).join("");
  table.querySelectorAll("[data-unpin]").forEach((b) => b.addEventListener("click", () => {
    state.pinned.splice(Number(b.dataset.unpin), 1);
    renderComparison();
  }));
  markScrollable(table.parentElement);
}

function csvCell(v) {
  const text = v === null || v === undefined ? "" : String(v);
  return /[",\n]/.test(text) ? `"${text.replace(/"/g, '""')}"` : text;
}

function comparisonCsv() {
  const fields = ["band", "sca", "metric", "mode", "solved_for", "precision", "tolerance", "magnitude", "uncertainty",
    "uncertainty_statistical", "uncertainty_fidelity", "uncertainty_optical_model", "uncertainty_model", "fidelity", "exptime",
    "beta0", "full_well", "stars", "saturation_magnitude"];
  const lines = [`# nlpsf comparison; ${state.meta ? `code ${state.meta.code_version}; optical data: ${state.meta.data_version}` : ""}`,
    "# units: precision and its uncertainties are fractions of beta0 (the page shows them in %); tolerance dimensionless; magnitudes AB mag; exposure s; beta0 1/e-; full_well e-",
    [...fields, "shear_budget", "scene", "sentence"].join(",")];
  for (const s of state.pinned) {
    lines.push([...fields.map((f) => csvCell(s[f])), csvCell(s.shear ? shearText(s.shear) : ""), csvCell(sceneName(s)), csvCell(answerSentence(s))].join(","));
  }
  downloadText(`nlpsf-comparison-${state.pinned.length}-answers.csv`, lines.join("\n") + "\n", "text/csv");
}

// ---- one answer as JSON and as ECSV -----------------------------------------------------------

function answerFileName(s, extension) {
  return `nlpsf-answer-${s.band}-sca${s.sca}-${s.metric}-${s.mode}-${s.solved_for}.${extension}`;
}

function downloadJson() {
  const s = state.lastSolution;
  if (!s || !state.current) return;
  const text = JSON.stringify({ request: state.lastRequest, answer: s, sentence: answerSentence(s), link: location.href }, null, 2);
  downloadText(answerFileName(s, "json"), text + "\n", "application/json");
}

// ECSV 1.0 (astropy's format): a YAML header (JSON is YAML) with the conditions, then one row per quantity.
function answerEcsv(s) {
  const rows = [
    ["precision", s.precision, "", "calibration precision, fraction of beta0"],
    ["tolerance", s.tolerance, "", "tolerated error of the PSF quantity"],
    ["magnitude", s.magnitude, "mag(AB)", "star magnitude"],
    ["uncertainty", s.uncertainty, s.solved_for === "magnitude" ? "mag(AB)" : "", `1-sigma uncertainty of the ${s.solved_for}`],
    ["uncertainty_statistical", s.uncertainty_statistical, "", "statistical part"],
    ["uncertainty_fidelity", s.uncertainty_fidelity, "", "method (fidelity) part"],
    ["uncertainty_optical_model", s.uncertainty_optical_model, "", "optical-model part"],
    ["uncertainty_model", s.uncertainty_model, "", "effects not modelled"],
    ["slope", s.slope, "electron", "slope c(m)"],
    ["slope_uncertainty", s.slope_uncertainty, "electron", "1-sigma uncertainty of the slope"],
    ["saturation_magnitude", s.saturation_magnitude, "mag(AB)", "saturation limit"],
    ["beta0", s.beta0, "1/electron", "NL coefficient"],
    ["exptime", s.exptime, "s", "exposure time"],
    ["full_well", s.full_well, "electron", "full-well depth"],
  ];
  const meta = {
    solved_for: s.solved_for, band: s.band, sca: s.sca, metric: s.metric, mode: s.mode, fidelity: s.fidelity, stars: s.stars,
    sentence: answerSentence(s), scene: sceneName(s), shear: s.shear, flags: s.flags, conditions: s.conditions, link: location.href,
  };
  const header = [
    "# %ECSV 1.0",
    "# ---",
    "# datatype:",
    "# - {name: quantity, datatype: string}",
    "# - {name: value, datatype: float64}",
    "# - {name: unit, datatype: string}",
    "# - {name: description, datatype: string}",
    `# meta: ${JSON.stringify(meta)}`,
    "# schema: astropy-2.0",
  ];
  const cell = (v) => (v === null || v === undefined || !Number.isFinite(v) ? "nan" : String(v));
  const quote = (t) => `"${String(t).replace(/"/g, '""')}"`;
  const body = ["quantity value unit description", ...rows.map(([q, v, u, d]) => `${q} ${cell(v)} ${quote(u)} ${quote(d)}`)];
  return [...header, ...body].join("\n") + "\n";
}

function downloadEcsv() {
  const s = state.lastSolution;
  if (!s || !state.current) return;
  downloadText(answerFileName(s, "ecsv"), answerEcsv(s), "text/plain");
}

// ---- batch -------------------------------------------------------------------------------------

async function runBatch(event) {
  event.preventDefault();
  const form = document.getElementById("batch-form");
  const box = document.getElementById("batch-error");
  clearError(box, form);
  const text = document.getElementById("batch-text").value;
  try {
    const answer = await api("/page/batch", { method: "POST", body: text, headers: { "Content-Type": "text/csv" } });
    state.batch = { text, answer };
    showBatch(answer);
  } catch (error) {
    if (error.unreachable) connection.lost("batch", () => runBatch(new Event("submit")));
    showError(box, form, error);
  }
}

function showBatch(answer) {
  document.getElementById("batch-summary").textContent = `${answer.answered} answered, ${answer.failed} refused.`;
  const table = document.getElementById("batch-table");
  table.tHead.innerHTML = "<tr><th scope=\"col\">row</th><th scope=\"col\">band</th><th scope=\"col\">detector</th><th scope=\"col\">PSF quantity</th>" +
    "<th scope=\"col\">answer</th><th scope=\"col\">notes</th></tr>";
  table.tBodies[0].innerHTML = answer.results.map((r) => {
    const s = r.solution;
    const request = answer.requests[r.index] || {};
    if (!s) {
      return `<tr class="refused"><th scope="row">${r.index + 1}</th><td>${escapeHtml(request.band || "")}</td><td>${escapeHtml(request.sca ?? "")}</td>` +
        `<td>${escapeHtml(request.metric || "")}</td><td>refused</td><td class="flags-cell">${escapeHtml(plainWords(r.error ? r.error.detail : ""))}</td></tr>`;
    }
    return `<tr><th scope="row">${r.index + 1}</th><td>${escapeHtml(s.band)}</td><td>${s.sca}</td><td>${escapeHtml(METRIC_LABEL[s.metric])}</td>` +
      `<td>${escapeHtml(answerHeadline(s))}</td><td class="flags-cell">${escapeHtml(s.flags.map(plainWords).join("; "))}</td></tr>`;
  }).join("");
  document.getElementById("batch-result").hidden = false;
  markScrollable(table.parentElement);
}

async function batchCsv() {
  if (!state.batch) return;
  try {
    const text = await api("/page/batch?format=csv", { method: "POST", body: state.batch.text, headers: { "Content-Type": "text/csv" }, raw: true });
    downloadText("nlpsf-batch-answers.csv", text, "text/csv");
  } catch (error) {
    showError(document.getElementById("batch-error"), null, error);
  }
}

// ---- start ------------------------------------------------------------------------------------

const SETTING_NAMES = { exptime_s: "exposure [s]", beta0: "β₀ [1/e⁻]", oversampling: "oversampling", stamp: "stamp [fine px]",
  realizations: "random centroids", seed: "seed", weight_cut_rho2: "weight cut ρ²", pupil_scale: "pupil scale rule" };

async function init() {
  const [meta, presets] = await Promise.all([api("/meta"), api("/page/presets")]);
  state.meta = meta;
  state.presets = presets;
  const d = meta.defaults.solve;
  const bands = meta.table_bands && meta.table_bands.length ? meta.table_bands : meta.bands;
  document.getElementById("versions").textContent = `code ${meta.code_version} · optical data: ${meta.data_version}`;
  const settings = (meta.tables && meta.tables.settings) || {};
  document.getElementById("table-version").textContent =
    Object.entries(settings).filter(([k]) => SETTING_NAMES[k]).map(([k, v]) => `${SETTING_NAMES[k]} ${v}`).join(" · ") +
    (meta.tables ? ` · version ${String(meta.tables.fingerprint).slice(0, 12)}` : "");
  fillSelect(document.getElementById("solve-band"), bands, meta.defaults.simulation.band || "H158");
  fillSelect(document.getElementById("solve-sca"), meta.scas, d.sca);
  for (const id of ["solve-metric", "slopes-metric", "beta-metric", "sigma-metric"]) {
    fillSelect(document.getElementById(id), meta.metrics, d.metric, (m) => METRIC_NAME[m] || m);
  }
  fillSelect(document.getElementById("solve-mode"), meta.modes, d.mode, (m) => MODE_NAME[m] || m);
  fillSelect(document.getElementById("slopes-mode"), meta.modes, d.mode, (m) => MODE_NAME[m] || m);
  fillSelect(document.getElementById("solve-fidelity"), meta.fidelities, d.fidelity || "table", fidelityName);
  for (const id of ["beta-band", "sigma-band", "sim-band"]) fillSelect(document.getElementById(id), bands, "H158");
  fillSelect(document.getElementById("sim-sca"), meta.scas, 18);
  fillSelect(document.getElementById("sim-fidelity"), meta.simulation_fidelities, "monte_carlo", fidelityName);
  fillReadout("solve");
  fillReadout("sim");
  exposurePlaceholder();
  document.getElementById("solve-scene").addEventListener("change", exposurePlaceholder);
  fillPresets();
  fillExplanations();

  document.getElementById("solve-form").addEventListener("submit", solve);
  // An edit after an answer greys it: it answers the question before the edit.
  for (const type of ["input", "change"]) document.getElementById("solve-form").addEventListener(type, () => formEdited());
  document.getElementById("scene-form").addEventListener("change", () => {
    if (document.getElementById("solve-scene").value === "custom") formEdited();
  });
  document.getElementById("calc-paper").addEventListener("change", () => {
    stateToUrl();
    if (state.lastRequest && state.current) drawAnswerPlots(state.lastRequest, state.lastSolution).catch(() => {});
  });
  document.getElementById("hint-position").textContent = "Position empty: the answer holds everywhere on the SCA (its most demanding field-grid position).";
  const limit = meta.limits && meta.limits.max_wavelengths;
  document.getElementById("hint-sim-wavelengths").textContent = `Wavelengths for the star's colour: empty, chosen for 0.1 % of the slopes` +
    `${limit ? `, at most ${limit} (this server's limit)` : ""}.`;
  document.querySelectorAll('input[name="solve_for"]').forEach((r) => r.addEventListener("change", updateUnknown));
  for (const name of ["shear_m", "shear_c"]) document.getElementById(`solve-${name}`).addEventListener("input", updateUnknown);
  document.getElementById("solve-precision").addEventListener("input", precisionHint);
  document.getElementById("sim-form").addEventListener("submit", runSimulation);
  document.getElementById("sim-csv").addEventListener("click", simulationCsv);
  document.getElementById("scene-form").addEventListener("submit", measureImpact);
  document.getElementById("scene-preset").addEventListener("change", (e) => sceneFill(e.target.value || "paper"));
  document.getElementById("batch-form").addEventListener("submit", runBatch);
  document.getElementById("batch-csv").addEventListener("click", batchCsv);
  document.getElementById("batch-file").addEventListener("change", async (e) => {
    const file = e.target.files[0];
    if (!file) return;
    document.getElementById("batch-text").value = await file.text();
    runBatch(new Event("submit"));
  });
  document.getElementById("pin-answer").addEventListener("click", pinAnswer);
  document.getElementById("download-json").addEventListener("click", downloadJson);
  document.getElementById("download-ecsv").addEventListener("click", downloadEcsv);
  document.getElementById("copy-link").addEventListener("click", copyLink);
  document.getElementById("compare-csv").addEventListener("click", comparisonCsv);
  document.getElementById("compare-clear").addEventListener("click", () => { state.pinned = []; renderComparison(); });
  document.querySelectorAll("[data-png]").forEach((b) => b.addEventListener("click", () => exportPng(b.dataset.png)));
  document.querySelectorAll("[data-csv]").forEach((b) => b.addEventListener("click", () => exportCsv(b.dataset.csv)));
  const redraw = () => { drawCurves(); stateToUrl(); };
  for (const id of ["slopes-metric", "slopes-mode", "beta-band", "beta-metric", "beta-log", "sigma-band", "sigma-metric", "sigma-log"]) {
    document.getElementById(id).addEventListener("change", redraw);
  }
  for (const id of ["beta-magnitude", "sigma-magnitude", "solve-sca", "solve-exptime", "solve-beta0", "solve-full_well"]) {
    document.getElementById(id).addEventListener("change", () => drawCurves());
  }
  document.getElementById("paper-overlay").addEventListener("change", async () => {
    if (!state.paper) state.paper = await api("/paper");
    redraw();
  });
  let resizeTimer = null;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => {
      for (const [name, u] of Object.entries(state.plots)) {
        const el = document.getElementById(`plot-${name}`);
        u.setSize({ width: Math.max(280, el.clientWidth), height: 320 });
      }
    }, 150);
  });
  stateFromUrl();
  loadPinned();
  if (document.getElementById("paper-overlay").checked) state.paper = await api("/paper");
  updateUnknown();
  await Promise.allSettled([solve(null), drawCurves()]);
  const job = sessionStorage.getItem("nlpsf-job");
  if (job) followJob({ id: job, status: "running", progress: 0, message: "following the simulation started before this page loaded" });
  document.body.dataset.ready = "true";
}

document.addEventListener("DOMContentLoaded", () => {
  init().catch((error) => {
    const box = document.getElementById("solve-error");
    showError(box, null, new ApiError(`the page could not load its data: ${error.message}`));
    if (error.unreachable) connection.lost("init", () => location.reload());
    document.body.dataset.ready = "error";
  });
});

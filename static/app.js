// The nlpsf page: calculator, curves and fresh simulations over the REST API (/api/v1).
// Plain JavaScript and the vendored uPlot; no build step, no network beyond this server.
"use strict";

const API = "api/v1";
const BAND_COLORS = {
  R062: "#7b3294", Z087: "#3b4cc0", Y106: "#2c7fb8", J129: "#1b9e77",
  H158: "#d95f02", F184: "#a6761d", W146: "#666666", K213: "#e7298a",
};
const METRIC_LABEL = { size: "ΔR/R", e1: "Δe₁", e2: "Δe₂", e: "|Δe|" };
const METRIC_KEY = { size: "dR_over_R", e1: "de1", e2: "de2" };
const state = { meta: null, paper: null, plots: {}, exports: {}, lastSimulation: null, polling: null };

class ApiError extends Error {
  constructor(message, field, status) {
    super(message);
    this.field = field;
    this.status = status;
  }
}

async function api(path, options = {}) {
  const response = await fetch(`${API}${path}`, {
    ...options,
    headers: { "Content-Type": "application/json", ...(options.headers || {}) },
  });
  let body = null;
  try {
    body = await response.json();
  } catch (_) {
    body = null;
  }
  if (!response.ok) {
    const message = body && body.message ? body.message : `the server answered ${response.status}`;
    throw new ApiError(message, body ? body.field : null, response.status);
  }
  return body;
}

// ---- formatting -------------------------------------------------------------------------

function fmt(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "n/a";
  const a = Math.abs(x);
  if (a !== 0 && (a >= 1e5 || a < 1e-3)) return x.toExponential(digits - 1);
  return Number(x.toPrecision(digits)).toString();
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

function showError(box, form, error) {
  box.textContent = error.message;
  box.hidden = false;
  if (form) {
    form.querySelectorAll("[aria-invalid]").forEach((el) => el.removeAttribute("aria-invalid"));
    if (error.field && form.elements[error.field]) form.elements[error.field].setAttribute("aria-invalid", "true");
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

// Draw (or redraw) plot `name` in its container. `columns` = [{label, x, y, series}], joined on x.
// `markers` = [{x, label, color}]: dashed vertical lines (e.g. saturation limits), kept in view.
function drawPlot(name, { xLabel, yLabel, columns, logX = false, logY = false, title, markers = [] }) {
  const el = document.getElementById(`plot-${name}`);
  const usable = columns.map((c) => {
    const keep = c.x.map((x, i) => x !== null && c.y[i] !== null && (!logX || x > 0) && (!logY || c.y[i] > 0));
    const err = c.err ? c.err.filter((_, i) => keep[i]) : null;
    return { ...c, x: c.x.filter((_, i) => keep[i]), y: c.y.filter((_, i) => keep[i]), err };
  }).filter((c) => c.x.length > 0);
  state.exports[name] = { title, xLabel, yLabel, columns: usable, markers };
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
  const axisValues = (u, values) => values.map((v) => (v === null ? "" : fmt(v, 3)));
  const options = {
    width: Math.max(320, el.clientWidth || 800),
    height: 320,
    scales: {
      x: { time: false, distr: logX ? 3 : 1,
        ...(markers.length ? { range: (u, lo, hi) => [Math.min(lo, ...markers.map((m) => m.x - 0.25)),
          Math.max(hi, ...markers.map((m) => m.x + 0.25))] } : {}) },
      y: { distr: logY ? 3 : 1 },
    },
    // Before the series, so that a point on a limit stays visible.
    hooks: { drawClear: [(u) => drawMarkers(u, markers)] },
    axes: [
      { label: xLabel, values: axisValues },
      { label: yLabel, values: axisValues, size: 70 },
    ],
    series: [{ label: xLabel, value: (u, v) => (v == null ? "–" : fmt(v)) },
      ...usable.map((c) => {
        // Hover shows each value with its uncertainty, looked up by x (the joined data has gaps).
        const errors = c.err ? new Map(c.x.map((x, i) => [x, c.err[i]])) : null;
        return { ...c.series, value: (u, v, si, i) => {
          if (v == null) return "–";
          const error = errors && i != null ? errors.get(u.data[0][i]) : undefined;
          return error == null ? fmt(v) : `${fmt(v)} ± ${fmt(error, 2)}`;
        } };
      })],
    legend: { live: true },
    cursor: { points: { size: 8 } },
  };
  state.plots[name] = new uPlot(options, data, el);
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

function exportPng(name) {
  const u = state.plots[name];
  const plot = state.exports[name];
  if (!u || !plot) return;
  const source = u.ctx.canvas;
  const scale = source.width / u.width;
  const legend = plot.columns.map((c) => c.label);
  const titleLines = plot.title.split("\n");
  const top = (16 * titleLines.length + 8) * scale;
  const bottom = (16 * legend.length + 8) * scale;
  const canvas = document.createElement("canvas");
  canvas.width = source.width;
  canvas.height = source.height + top + bottom;
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#fff";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#1d2330";
  ctx.font = `${12 * scale}px sans-serif`;
  titleLines.forEach((line, i) => ctx.fillText(line, 8 * scale, (16 * (i + 1)) * scale));
  ctx.drawImage(source, 0, top);
  plot.columns.forEach((c, i) => {
    ctx.fillStyle = c.series.stroke || "#000";
    ctx.fillText(`● ${c.label}`, 8 * scale, top + source.height + (16 * (i + 1)) * scale);
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

async function solve(event) {
  if (event) event.preventDefault();
  const form = document.getElementById("solve-form");
  const errorBox = document.getElementById("solve-error");
  const resultBox = document.getElementById("solve-result");
  clearError(errorBox, form);
  const unknown = form.elements.solve_for.value;
  const body = {
    band: form.elements.band.value,
    sca: numberOrText(form.elements.sca.value),
    metric: form.elements.metric.value,
    mode: form.elements.mode.value,
    beta0: numberOrText(form.elements.beta0.value),
    exptime: numberOrText(form.elements.exptime.value),
    full_well: numberOrText(form.elements.full_well.value),
    fidelity: form.elements.fidelity.value,
    ...readoutFields("solve"),
  };
  for (const name of ["precision", "tolerance", "magnitude"]) {
    if (name === unknown) continue;
    const value = numberOrText(form.elements[name].value);
    if (value === null) {
      showError(errorBox, form, new ApiError(`${name}: enter a value (give two of precision, tolerance, magnitude)`, name));
      return;
    }
    body[name] = value;
  }
  try {
    const s = await api("/solve", { method: "POST", body: JSON.stringify(body) });
    form.elements[s.solved_for].value = fmt(s[s.solved_for], 5);
    const names = { precision: "precision p", tolerance: `tolerance T (${METRIC_LABEL[s.metric]})`, magnitude: "magnitude m" };
    resultBox.innerHTML = `
      <div class="answer" data-testid="solve-answer">${escapeHtml(names[s.solved_for])} = ${escapeHtml(plusMinus(s[s.solved_for], s.uncertainty))}</div>
      <div>precision ${fmt(s.precision)} · tolerance ${fmt(s.tolerance)} · magnitude ${fmt(s.magnitude)}
        · slope c(m) = ${fmt(s.slope)} · saturation at m = ${fmt(s.saturation_magnitude)}${s.conditions.ramp
          ? ` (first resultant; a single final frame: m = ${fmt(s.final_frame_saturation_magnitude)})` : ""}</div>
      ${s.conditions.ramp ? `<div class="muted">slopes from ${escapeHtml(s.conditions.ramp_slopes_from)}</div>` : ""}
      ${s.flags && s.flags.length ? `<ul class="flags">${s.flags.map((f) => `<li>${escapeHtml(f)}</li>`).join("")}</ul>` : ""}
      <p class="conditions">${escapeHtml(conditionsText({ ...s.conditions, band: s.band, sca: s.sca, exptime_s: s.exptime, beta0: s.beta0, fidelity: s.fidelity }))}
        · ${escapeHtml(s.mode)} of ${escapeHtml(METRIC_LABEL[s.metric])}</p>`;
    resultBox.hidden = false;
    await drawCalculatorPlot(s);
  } catch (error) {
    resultBox.hidden = true;
    showError(errorBox, form, error);
  }
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
    { label, x: curve.magnitude, y: curve.slope.map(abs), err: curve.uncertainty,
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
    y: [abs(solution.slope)], series: pointSeries("answer", "#c00000", 12) });
  drawPlot("calc", {
    markers,
    title: `${label} vs magnitude; answer marked${ramp ? `; up the ramp: ${ramp.description}` : ""}\n${conditionsText(curve.conditions)}`,
    xLabel: "magnitude (AB)",
    yLabel: `${solution.mode === "bias" ? "d" : "σ"}(${METRIC_LABEL[solution.metric]})/${solution.mode === "bias" ? "dβ" : "σβ"} [e⁻]`,
    logY: true,
    columns,
  });
  document.getElementById("plot-calc").dataset.point = `${solution.magnitude},${solution.slope}`;
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

function simulationPoints(kind, band, metric, magnitude) {
  const sim = state.lastSimulation;
  if (!sim || metric === "e") return [];
  const key = METRIC_KEY[metric];
  const rows = sim.results.filter((r) => r.band === band && Math.abs(r.magnitude - magnitude) < 1e-9 &&
    (kind === "beta" ? r.sigma_beta === 0 : r.sigma_beta > 0));
  if (rows.length === 0) return [];
  const x = rows.map((r) => (kind === "beta" ? r.beta : r.sigma_beta));
  const y = rows.map((r) => (kind === "beta" ? r[key].mean : r[key].std));
  // The standard error of a mean; for a spread over n draws, std / sqrt(2(n - 1)).
  const err = rows.map((r) => (kind === "beta" ? r[key].stderr : r[key].std / Math.sqrt(2 * Math.max(r.realizations - 1, 1))));
  const label = `fresh simulation (${sim.fidelity}, ${rows[0].realizations} realizations)`;
  return [{ label, x, y, err, series: pointSeries(label, "#c00000", 9) }];
}

async function drawBeta() {
  const c = sharedConditions();
  const band = document.getElementById("beta-band").value;
  const metric = document.getElementById("beta-metric").value;
  const magnitude = document.getElementById("beta-magnitude").value.trim();
  const log = document.getElementById("beta-log").checked;
  const data = await api(`/curves/beta?${query({ band, metric, magnitude, ...c })}`);
  const label = `${band}, m = ${fmt(data.magnitude)} (table, first order)`;
  const columns = [{ label, x: data.beta, y: data.values, err: data.uncertainty, series: lineSeries(label, BAND_COLORS[band] || "#333") }];
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
    `Slope c = ${fmt(data.slope)} per unit β (relative uncertainty ${fmt(data.uncertainty.at(-1) / Math.abs(data.values.at(-1)), 2)}).` +
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
  const columns = [{ label, x: data.sigma_beta, y: data.values, err: data.uncertainty,
    series: lineSeries(label, BAND_COLORS[band] || "#333") }];
  columns.push(...simulationPoints("sigma", band, metric, Number(magnitude)));
  const title = `σ(${METRIC_LABEL[metric]}) vs σβ at m = ${fmt(data.magnitude)}\n${conditionsText(data.conditions)}`;
  document.getElementById("sigma-caption").textContent = `${data.source}. ${conditionsText(data.conditions)}. ` +
    `Scatter slope = ${fmt(data.slope)} per unit σβ.` + (data.flags.length ? ` Flags: ${data.flags.join("; ")}` : "");
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
    showImpact(await api("/impact", { method: "POST", body: JSON.stringify(body) }));
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

// The page's calibration section: the response kernel K(Q) of the calculator's star and the bias a
// calibration residual leaves (POST /api/v1/calibration/kernel and /residual, docs/calibration.md).
// It draws and formats; every number comes from the API. It reads the calculator's form by its field
// names (band, sca, metric, beta0, exptime, full_well, magnitude, scene, position, readout) and keeps
// to itself otherwise: its own state, its own plot (the vendored uPlot), its own job following.
"use strict";

(() => {
  const API = "api/v1";
  const METRICS = { size: "size ΔR/R", e1: "ellipticity Δe₁", e2: "ellipticity Δe₂", e: "ellipticity |Δe|" };
  // Plain names for the fields a refusal may name.
  const FIELDS = {
    band: "band", sca: "detector (SCA)", magnitude: "magnitude", beta0: "nonlinearity β₀", exptime: "exposure",
    full_well: "full well", scene: "scene", "scene.position": "position on the detector", ramp: "number of reads",
    ma_table: "readout", ramp_fit: "ramp fit", residual: "residual", "residual.curve": "residual curve",
    "residual.polynomial": "polynomial coefficients", "residual.shape": "shape", "residual.scale": "scale",
    "residual.linearity": "per-pixel coefficients",
  };
  const cal = { kernel: null, kernelJob: null, plot: null, running: null, keyIdx: null };
  window.calibrationState = cal; // for the browser tests

  const $ = (id) => document.getElementById(id);

  // The page's number format (app.js): plain between 1e-3 and 1e5, else mantissa e exponent.
  function fmt(x, digits = 4) {
    if (x === null || x === undefined || !Number.isFinite(x)) return "–";
    const a = Math.abs(x);
    if (a !== 0 && (a >= 1e5 || a < 1e-3)) {
      const [mantissa, exponent] = x.toExponential(digits - 1).split("e");
      return `${Number(mantissa)}e${Number(exponent)}`;
    }
    return Number(x.toPrecision(digits)).toString();
  }

  function withError(value, error) {
    if (!Number.isFinite(error) || error <= 0) return fmt(value);
    return `${fmt(value)} ± ${fmt(error, 2)}`;
  }

  function escapeHtml(text) {
    return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
  }

  class Refusal extends Error {
    constructor(message, field = null) {
      super(message);
      this.field = field;
    }
  }

  function fieldName(field) {
    return FIELDS[field] || String(field || "").replace(/_/g, " ");
  }

  // ---- the calculator's star ------------------------------------------------------------------

  function value(id) {
    const el = $(id);
    return el && !el.disabled ? el.value.trim() : "";
  }

  function number(id, field, optional = false) {
    const text = value(id);
    if (text === "") {
      if (optional) return undefined;
      throw new Refusal(`${fieldName(field)}: enter a value in the calculator`, field);
    }
    const x = Number(text);
    if (!Number.isFinite(x)) throw new Refusal(`${fieldName(field)}: "${text.slice(0, 40)}" is not a number`, field);
    return x;
  }

  function position() {
    for (const id of ["solve-position", "scene-position"]) {
      const text = value(id);
      if (!text) continue;
      const parts = text.split(/[\s,]+/).filter(Boolean).map(Number);
      if (parts.length !== 2 || !parts.every(Number.isFinite)) {
        throw new Refusal(`${fieldName("scene.position")}: give X,Y in pixels, e.g. 900,3100`, "scene.position");
      }
      return parts;
    }
    return null;
  }

  // The calculator's request, as POST /api/v1/solve would take it, without the two-of-three.
  function starRequest() {
    const body = {
      band: value("solve-band") || "H158",
      sca: Number(value("solve-sca") || 18),
      metric: value("solve-metric") || "size",
      magnitude: number("solve-magnitude", "magnitude"),
    };
    const beta0 = number("solve-beta0", "beta0", true);
    if (beta0 !== undefined) body.beta0 = beta0;
    const exptime = number("solve-exptime", "exptime", true);
    if (exptime !== undefined) body.exptime = exptime;
    const fullWell = number("solve-full_well", "full_well", true);
    if (fullWell !== undefined) body.full_well = fullWell;
    const readout = value("solve-readout");
    const fit = value("solve-ramp_fit");
    if (readout === "uniform") Object.assign(body, { ramp: number("solve-ramp", "ramp"), ...(fit ? { ramp_fit: fit } : {}) });
    else if (readout.startsWith("table:")) Object.assign(body, { ma_table: readout.slice(6), ...(fit ? { ramp_fit: fit } : {}) });
    const where = position();
    const preset = value("solve-scene");
    if (preset === "paper" || preset === "galsim-roman") body.scene = where ? { preset, position: where } : preset;
    else if (where) body.scene = { position: where };
    return body;
  }

  function starWords(body) {
    const scene = body.scene === undefined ? "the Roman default scene" : (body.scene === "paper" || body.scene.preset === "paper")
      ? "the paper's scene" : body.scene === "galsim-roman" || body.scene.preset === "galsim-roman" ? "GalSim's Roman constants"
        : "the Roman default scene";
    const where = body.scene && body.scene.position ? `at (${body.scene.position.join(", ")})` : "at the SCA centre";
    return `${body.band}, SCA ${body.sca}, m = ${body.magnitude}, ${where}, ${scene}`;
  }

  function describeStar() {
    const line = $("kernel-star");
    try {
      line.textContent = `For the calculator's star: ${starWords(starRequest())}.`;
    } catch (error) {
      line.textContent = `For the calculator's star (${error.message}).`;
    }
  }

  // ---- asking the API, following a job -----------------------------------------------------

  function problemOf(body, status) {
    const field = body && body.field ? body.field : null;
    let message = body && (body.detail || body.message) ? String(body.detail || body.message) : `the server answered ${status}`;
    if (field && message.startsWith(`${field}: `)) message = `${fieldName(field)}: ${message.slice(field.length + 2)}`;
    return new Refusal(message, field);
  }

  async function ask(path, body, progress, started) {
    let response;
    try {
      response = await fetch(`${API}${path}`, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    } catch (_) {
      throw new Refusal("the nlpsf server cannot be reached");
    }
    const answer = await response.json().catch(() => null);
    const location = response.headers.get("Location");
    const jobId = location ? location.split("/").pop() : null;
    if (!response.ok) throw problemOf(answer, response.status);
    if (response.status !== 202) return { result: answer, jobId };
    if (started) started(jobId);
    return { result: await follow(jobId, progress), jobId };
  }

  async function follow(jobId, progress) {
    for (;;) {
      await new Promise((resolve) => setTimeout(resolve, 400));
      let job;
      try {
        const response = await fetch(`${API}/simulations/${jobId}`, { cache: "no-store" });
        job = await response.json();
        if (!response.ok) throw problemOf(job, response.status);
      } catch (error) {
        if (error instanceof Refusal) throw error;
        continue; // a lost connection: ask again
      }
      if (progress) progress(job.progress || 0, job.message || job.status);
      if (job.status === "done") return job.result;
      if (["failed", "cancelled", "interrupted"].includes(job.status)) {
        const error = job.error || {};
        if (error.field) throw new Refusal(`${fieldName(error.field)}: ${error.message}`, error.field);
        throw new Refusal(`the simulation ${job.status}${job.message ? `: ${job.message}` : ""}`);
      }
    }
  }

  function showError(id, error) {
    const box = $(id);
    box.hidden = false;
    box.textContent = error.message;
  }

  function setProgress(fraction, message) {
    $("kernel-progress").value = fraction;
    $("kernel-progress-text").textContent = message;
  }

  // ---- the kernel --------------------------------------------------------------------------

  async function computeKernel(event) {
    if (event) event.preventDefault();
    $("kernel-error").hidden = true;
    let body;
    try {
      body = starRequest();
    } catch (error) {
      showError("kernel-error", error);
      return;
    }
    const button = $("kernel-button");
    button.disabled = true;
    setProgress(0, "asking the server");
    const asked = (cal.asked = (cal.asked || 0) + 1);
    try {
      const { result, jobId } = await ask("/calibration/kernel", body, setProgress, (id) => {
        cal.running = id;
        $("kernel-cancel").disabled = false;
      });
      if (asked !== cal.asked) return;
      cal.kernel = result;
      cal.kernelJob = jobId;
      cal.star = body;
      setProgress(1, "done");
      if (METRICS[result.metric]) $("kernel-metric").value = result.metric;
      const link = $("kernel-ecsv");
      link.href = `${API}/calibration/kernel/${jobId}.ecsv`;
      link.setAttribute("download", `nlpsf-kernel-${body.band}-sca${body.sca}-m${body.magnitude}.ecsv`);
      link.hidden = false;
      drawKernel();
    } catch (error) {
      if (asked !== cal.asked) return;
      setProgress(0, "no kernel");
      showError("kernel-error", error);
    } finally {
      if (asked === cal.asked) {
        button.disabled = false;
        cal.running = null;
        $("kernel-cancel").disabled = true;
      }
    }
  }

  async function cancelKernel() {
    if (!cal.running) return;
    await fetch(`${API}/simulations/${cal.running}`, { method: "DELETE" }).catch(() => null);
  }

  // The kernel in tenths of a decade of charge (the API's fractional_bins): bar i spans edges i to i + 1.
  function kernelBins(metric) {
    const bins = cal.kernel.fractional_bins;
    return { edges: bins.edges_e, y: bins[metric], e: bins[`${metric}_err`] };
  }

  function marks() {
    const meta = cal.kernel.meta;
    return [
      { x: meta.full_well_e, label: `full well: ${fmt(meta.full_well_e, 6)} e⁻ of signal`, color: "#6a3d9a", dash: [6, 4] },
      { x: meta.saturation_e, label: `saturation: the charge whose signal reaches the full well, ${fmt(meta.saturation_e, 6)} e⁻`, color: "#a4161a", dash: [2, 3] },
    ];
  }

  function drawKernel() {
    const metric = $("kernel-metric").value;
    const meta = cal.kernel.meta;
    const { edges, y, e } = kernelBins(metric);
    const [low, high] = meta.signal_range_e[metric] || [0, 0];
    const share = Math.round(100 * (meta.signal_fraction || 0.9));
    const el = $("plot-kernel");
    if (cal.plot) cal.plot.destroy();
    el.innerHTML = "";
    el.dataset.metric = metric;
    el.dataset.bins = String(y.length);
    const lines = marks();
    const top = Math.max(edges[edges.length - 1], ...lines.map((m) => m.x)) * 1.15;
    // A stepped line through each bin's value from its left edge: the last value is repeated at the last edge.
    const ys = [...y, y[y.length - 1]];
    const options = {
      width: Math.max(280, el.clientWidth || 800),
      height: 320,
      scales: { x: { time: false, distr: 3, range: () => [edges[0], top] }, y: { distr: 1 } },
      axes: [
        { label: "charge Q [e⁻]", values: (u, splits) => splits.map((v) => powerOfTen(v)), space: 50 },
        { label: "change per tenth of a decade, r = Q", size: 80, values: (u, splits) => splits.map((v) => fmt(v, 2)) },
      ],
      series: [
        { label: "Q [e⁻]", value: (u, v, si, i) => (i == null ? "–" : `${fmt(edges[i], 4)}–${fmt(edges[Math.min(i + 1, edges.length - 1)], 4)}`) },
        { label: METRICS[metric], stroke: "#0072B2", fill: "rgba(0,114,178,0.35)", width: 1.5, points: { show: false },
          paths: uPlot.paths.stepped({ align: 1 }), value: (u, v, si, i) => (i == null || i >= y.length ? "–" : withError(y[i], e[i])) },
      ],
      hooks: { drawClear: [(u) => drawBackground(u, low, high, lines)] },
      legend: { live: true },
      cursor: { points: { show: false } },
    };
    cal.plot = new uPlot(options, [edges, ys], el);
    cal.keyIdx = null;
    $("key-kernel").innerHTML = [
      `<span class="key-item"><span class="swatch" style="background-color:rgba(230,159,0,0.25)"></span>${share} % of a quadratic residual's effect on ${escapeHtml(METRICS[metric])}: ${fmt(low)}–${fmt(high)} e⁻</span>`,
      ...lines.map((m) => `<span class="key-item"><span class="swatch line" style="border-color:${m.color}"></span>${escapeHtml(m.label)}</span>`),
    ].join("");
    el.dataset.signalLow = String(low);
    el.dataset.signalHigh = String(high);
    const slope = meta.quadratic_slopes[metric];
    $("kernel-summary").innerHTML = `The charge levels that matter for this star's ${escapeHtml(METRICS[metric])}: <strong data-testid="kernel-range">${fmt(low)}–${fmt(high)} e⁻</strong> hold ${share} % of a quadratic residual's effect; a calibration must get its residual right there. ∫K(Q)(−Q²)dQ = ${escapeHtml(withError(slope.value, slope.uncertainty))} e⁻, the slope the calculator's Δβ acts through. ${meta.flags.length ? `Flags: ${escapeHtml(meta.flags.join("; "))}.` : ""}`;
    const c = meta.conditions || {};
    $("kernel-conditions").textContent = `Conditions: ${c.band}, SCA ${c.sca}, m = ${meta.magnitude} (${fmt(meta.flux_electrons, 6)} e⁻), ${c.scene_description || "scene"}, ${c.ramp ? c.ramp.description : "final frame"}, ${meta.realizations} centroid realizations; ${c.residual_nl}.`;
    renderTable(edges, y, e, metric);
    $("kernel-result").hidden = false;
  }

  const SUPERSCRIPT = { "-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷", 8: "⁸", 9: "⁹" };
  function powerOfTen(v) {
    const n = Math.log10(v);
    if (Math.abs(n - Math.round(n)) < 1e-9) return `10${String(Math.round(n)).split("").map((c) => SUPERSCRIPT[c]).join("")}`;
    return "";
  }

  function drawBackground(u, low, high, lines) {
    const ctx = u.ctx;
    const { top, height } = u.bbox;
    ctx.save();
    if (high > low) {
      const x0 = u.valToPos(Math.max(low, u.scales.x.min), "x", true);
      const x1 = u.valToPos(Math.min(high, u.scales.x.max), "x", true);
      ctx.fillStyle = "rgba(230,159,0,0.25)";
      ctx.fillRect(x0, top, x1 - x0, height);
    }
    const ratio = window.devicePixelRatio || 1;
    for (const m of lines) {
      if (!(m.x > u.scales.x.min && m.x < u.scales.x.max)) continue;
      const px = u.valToPos(m.x, "x", true);
      ctx.strokeStyle = m.color;
      ctx.lineWidth = 2 * ratio;
      ctx.setLineDash(m.dash.map((d) => d * ratio));
      ctx.beginPath();
      ctx.moveTo(px, top);
      ctx.lineTo(px, top + height);
      ctx.stroke();
    }
    ctx.restore();
  }

  function renderTable(edges, y, e, metric) {
    const rows = y.map((v, i) => `<tr><td>${fmt(edges[i], 4)}</td><td>${fmt(edges[i + 1], 4)}</td><td>${fmt(v, 4)}</td><td>${fmt(e[i], 2)}</td></tr>`).join("");
    $("kernel-table").innerHTML = `<thead><tr><th scope="col">from Q [e⁻]</th><th scope="col">to Q [e⁻]</th><th scope="col">${escapeHtml(METRICS[metric])} for r = Q</th><th scope="col">± (1σ)</th></tr></thead><tbody>${rows}</tbody>`;
  }

  // Arrow keys move the reading along the charge axis (Shift: ten nodes); Home and End jump to the ends.
  function keyboard(event) {
    const u = cal.plot;
    if (!u) return;
    const n = u.data[0].length - 1; // bins
    let idx = cal.keyIdx ?? Math.floor(n / 2);
    const step = event.shiftKey ? 10 : 1;
    if (event.key === "ArrowRight") idx = Math.min(n - 1, idx + step);
    else if (event.key === "ArrowLeft") idx = Math.max(0, idx - step);
    else if (event.key === "Home") idx = 0;
    else if (event.key === "End") idx = n - 1;
    else return;
    event.preventDefault();
    cal.keyIdx = idx;
    const [from, to] = [u.data[0][idx], u.data[0][idx + 1]];
    const v = u.data[1][idx];
    const metric = $("kernel-metric").value;
    const err = cal.kernel.fractional_bins[`${metric}_err`][idx];
    u.setCursor({ left: u.valToPos(Math.sqrt(from * to), "x"), top: v == null ? 0 : u.valToPos(v, "y") });
    $("kernel-readout").textContent = `Q = ${fmt(from, 4)}–${fmt(to, 4)} e⁻: ${METRICS[metric]} changes by ${withError(v, err)} for r = Q there`;
  }

  // ---- a residual ------------------------------------------------------------------------------

  function numbers(text, what) {
    const parts = text.split(/[\s,;]+/).filter(Boolean);
    const values = parts.map(Number);
    const bad = parts.findIndex((p, i) => !Number.isFinite(values[i]));
    if (bad >= 0) throw new Refusal(`${what}: "${parts[bad].slice(0, 30)}" is not a number`, what);
    return values;
  }

  function residualSpec() {
    const kind = $("residual-kind").value;
    if (kind === "polynomial") {
      const coefficients = numbers($("residual-polynomial").value, "polynomial coefficients");
      if (!coefficients.length) throw new Refusal("polynomial coefficients: give a₀, a₁, …", "residual.polynomial");
      return { polynomial: coefficients };
    }
    if (kind === "shape") {
      const family = $("residual-shape").value;
      const alpha = $("residual-alpha").value.trim();
      const scale = numbers($("residual-scale").value, "scale");
      if (scale.length !== 1) throw new Refusal("scale: give one number", "residual.scale");
      return { shape: family === "power_law" ? `power_law:${alpha || "1"}` : family, scale: scale[0] };
    }
    const rows = $("residual-curve").value.split(/\n/).map((line) => line.trim()).filter((line) => line && !/^[a-z#]/i.test(line));
    const charge = [];
    const residual = [];
    rows.forEach((line, i) => {
      const pair = numbers(line, `curve row ${i + 1}`);
      if (pair.length !== 2) throw new Refusal(`curve row ${i + 1}: give charge_e, residual_e`, "residual.curve");
      charge.push(pair[0]);
      residual.push(pair[1]);
    });
    return { curve: { charge_e: charge, residual_e: residual } };
  }

  function showKind() {
    const kind = $("residual-kind").value;
    for (const name of ["curve", "polynomial", "shape"]) $(`residual-${name}-box`).hidden = name !== kind;
    $("residual-alpha").disabled = $("residual-shape").value !== "power_law";
  }

  async function reportBias(event) {
    if (event) event.preventDefault();
    $("residual-error").hidden = true;
    const result = $("residual-result");
    let body;
    try {
      body = { ...starRequest(), residual: residualSpec() };
    } catch (error) {
      showError("residual-error", error);
      return;
    }
    const button = $("residual-button");
    button.disabled = true;
    result.classList.add("stale");
    try {
      const { result: effect } = await ask("/calibration/residual", body, (f, m) => { $("residual-status").textContent = m; });
      const rows = ["size", "e1", "e2", "e"].map((m) => {
        const b = effect.bias[m];
        return `<tr><th scope="row">${escapeHtml(METRICS[m])}</th><td data-testid="bias-${m}">${fmt(b.value, 5)}</td><td>${fmt(b.uncertainty, 2)}</td></tr>`;
      }).join("");
      $("residual-table").innerHTML = `<thead><tr><th scope="col">PSF quantity</th><th scope="col">bias (dimensionless)</th><th scope="col">± (1σ, statistical)</th></tr></thead><tbody>${rows}</tbody>`;
      const c = effect.conditions || {};
      $("residual-conditions").textContent = `For ${starWords(body)}: residual ${c.residual}. ${effect.flags.length ? `Flags: ${effect.flags.join("; ")}.` : ""}`;
      $("residual-status").textContent = "";
      result.hidden = false;
      result.classList.remove("stale");
      cal.bias = effect;
    } catch (error) {
      result.hidden = true;
      $("residual-status").textContent = "";
      showError("residual-error", error);
    } finally {
      button.disabled = false;
    }
  }

  function init() {
    const select = $("kernel-metric");
    if (!select) return;
    select.innerHTML = Object.entries(METRICS).map(([k, v]) => `<option value="${k}">${escapeHtml(v)}</option>`).join("");
    select.addEventListener("change", () => { if (cal.kernel) drawKernel(); });
    $("kernel-form").addEventListener("submit", computeKernel);
    $("kernel-cancel").addEventListener("click", cancelKernel);
    $("residual-form").addEventListener("submit", reportBias);
    $("residual-kind").addEventListener("change", showKind);
    $("residual-shape").addEventListener("change", showKind);
    const plot = $("plot-kernel");
    plot.tabIndex = 0;
    plot.setAttribute("role", "group");
    plot.setAttribute("aria-label", "response kernel plot: arrow keys read values");
    plot.addEventListener("keydown", keyboard);
    const form = $("solve-form");
    if (form) {
      form.addEventListener("input", describeStar);
      form.addEventListener("change", describeStar);
    }
    $("scene-position")?.addEventListener("input", describeStar);
    window.addEventListener("resize", () => {
      if (cal.plot) cal.plot.setSize({ width: Math.max(280, plot.clientWidth || 800), height: 320 });
    });
    showKind();
    describeStar();
    // The calculator's fields are filled (from the URL, the server's lists) once the page is ready.
    new MutationObserver(describeStar).observe(document.body, { attributes: true, attributeFilter: ["data-ready"] });
    document.body.dataset.calibrationReady = "true";
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();

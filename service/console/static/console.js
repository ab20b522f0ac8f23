// The operator console: read-only views of the model, its calibrations, coverage audits, live
// coverage from field labels and drift, drawn with plain DOM and inline SVG (no library, nothing fetched from elsewhere).
// Admin data needs the admin token; it is kept in this tab's sessionStorage only.
"use strict";

const TOKEN_KEY = "cks-admin-token";
const SVG = "http://www.w3.org/2000/svg";
const VERSIONS_SHOWN = 10;

const state = { model: null, audit: null, live: null, token: sessionStorage.getItem(TOKEN_KEY) || "" };

// ---------------------------------------------------------------- small helpers

function el(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  for (const child of children) node.append(child instanceof Node ? child : String(child));
  return node;
}

function svg(tag, attributes = {}, text) {
  const node = document.createElementNS(SVG, tag);
  for (const [name, value] of Object.entries(attributes)) node.setAttribute(name, value);
  if (text !== undefined) node.textContent = String(text);
  return node;
}

function panel(id) {
  return document.querySelector(`#${id} .body`);
}

function show(id, ...nodes) {
  panel(id).replaceChildren(...nodes);
}

function note(text, className = "muted") {
  return el("p", { class: className }, text);
}

function onlyNote(id, text) {
  // A panel with a note only: its controls (if any) hidden, its detail (if any) emptied.
  const section = document.getElementById(id);
  section.querySelectorAll(".controls").forEach((controls) => { controls.hidden = true; });
  section.querySelectorAll(".body ~ div:not(.controls)").forEach((detail) => detail.replaceChildren());
  show(id, note(text));
}

function table(headers, rows) {
  // Each cell names its column (data-label): on a phone a table with headers reads row by row.
  const head = el("tr", {}, ...headers.map((h) => el("th", {}, h)));
  const cell = (value, i) => {
    const attributes = headers[i] ? { "data-label": headers[i] } : {};
    if (typeof value === "number") attributes.class = "num";
    return el("td", attributes, value ?? "");
  };
  const body = rows.map((cells) => el("tr", {}, ...cells.map(cell)));
  return el("table", headers.some(Boolean) ? { class: "rows" } : {}, el("thead", {}, head), el("tbody", {}, ...body));
}

function fixed(value, digits = 3) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

function whenCell(text) {
  // A date in a table breaks between its day and its time, never at its hyphens or colons.
  const [day, ...time] = when(text).split(" ");
  return el("span", {}, el("span", { class: "nowrap" }, day), " ", el("span", { class: "nowrap" }, time.join(" ")));
}

function when(text) {
  if (!text) return "";
  const date = new Date(text);
  return Number.isNaN(date.getTime()) ? String(text) : date.toISOString().replace("T", " ").slice(0, 19) + " UTC";
}

class HttpError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

async function getJson(path, admin = true) {
  const headers = { Accept: "application/json" };
  if (admin) headers.Authorization = `Bearer ${state.token}`;
  const response = await fetch(path, { headers, cache: "no-store" });
  if (!response.ok) {
    let detail = response.statusText;
    try {
      detail = (await response.json()).detail || detail;
    } catch (ignored) { /* not JSON */ }
    throw new HttpError(response.status, detail);
  }
  return response.json();
}

function failure(error) {
  if (error instanceof HttpError && error.status === 401) return note("The admin token was refused: enter a valid one.", "fail");
  if (error instanceof HttpError && error.status === 403) return note("The admin API is disabled on this server (set CKS_ADMIN_TOKEN).", "fail");
  return note(`Could not load: ${error.message}`, "fail");
}

// ---------------------------------------------------------------- model

function keypointNames() {
  const keypoints = state.model?.manifest?.keypoints || [];
  return [...keypoints].sort((a, b) => a.index - b.index).map((k) => k.name);
}

function variantText(model) {
  const variant = model.manifest?.variant;
  return variant ? `${variant.name}, of ${variant.source_name}` : model.variant;
}

async function loadModel() {
  try {
    state.model = await getJson("v1/model", false);
  } catch (error) {
    show("model", failure(error));
    return;
  }
  const manifest = state.model.manifest || {};
  const objects = (manifest.objects || []).map((o) => `${o.name} (${(o.keypoints || []).length})`).join(", ");
  show("model", table(["", ""], [
    ["name", state.model.name],
    ["variant", variantText(state.model)],
    ["sha256", el("code", {}, state.model.hash)],
    ["service", state.model.service_version],
    ["keypoints", keypointNames().length],
    ["objects", objects],
    ["normalization", `${manifest.heatmap?.normalization ?? ""}, top-K ${manifest.heatmap?.top_k ?? ""}`],
  ]));
}

// ---------------------------------------------------------------- versions and activations

async function loadVersions() {
  const list = await getJson("v1/admin/calibrations");
  const versions = (list.versions || []).slice(-VERSIONS_SHOWN).reverse();
  const details = await Promise.all(versions.map((v) => getJson(`v1/admin/calibrations/${v.version}`)));
  const counts = (d) => Object.entries(d.labeled_per_keypoint || {});
  const rows = details.map((d) => {
    const least = counts(d).length ? Math.min(...counts(d).map(([, n]) => n)) : "–";
    return [d.version + (d.active ? " (active)" : ""), whenCell(d.created_at), d.author, d.instances, `min ${least}`,
      d.usable === false ? "unusable" : "", d.note || ""];
  });
  // Every keypoint's n under the table, as text that wraps: a column of them would not fit a phone.
  const perKeypoint = details.map((d) => el("details", {}, el("summary", {}, `n per keypoint, version ${d.version}`),
    note(counts(d).map(([k, n]) => `${k}\u00a0${n}`).join(" · "))));
  const shown = versions.length < (list.versions || []).length ? note(`The latest ${versions.length} versions.`) : "";
  show("versions", table(["version", "created", "author", "instances", "n per keypoint", "", "note"], rows),
    ...perKeypoint, shown);
}

async function loadActivations() {
  const log = await getJson("v1/admin/activations");
  const rows = [...(log.activations || [])].reverse().map((a) => [a.seq, a.version, whenCell(a.activated_at), a.who, a.reason]);
  show("activations", rows.length ? table(["seq", "version", "activated", "who", "reason"], rows) : note("No activation yet."));
}

// ---------------------------------------------------------------- audits

async function loadAudits() {
  const list = await getJson("v1/admin/audits?limit=20");
  const audits = list.audits || [];
  if (!audits.length) return onlyNote("audits", "No coverage audit yet: POST a labeled batch to /v1/admin/audits (docs/operations.md).");
  show("audits", table(["id", "version", "created", "who", "instances", "result"], audits.map((a) => [
    a.id, a.version, whenCell(a.created_at), a.who, a.instances,
    a.passed ? el("span", { class: "pass" }, "passed") : el("span", { class: "fail" }, `${a.flagged} flagged`),
  ])));
  const choice = document.getElementById("audit-choice");
  choice.replaceChildren(...audits.map((a) => el("option", { value: a.id }, `#${a.id} (version ${a.version})`)));
  document.querySelector("#audits .controls").hidden = false;
  await loadAudit(audits[0].id);
}

async function loadAudit(id) {
  state.audit = await getJson(`v1/admin/audits/${id}`);
  const sections = state.audit.report?.sections || [];
  fillSelect("audit-kind", [...new Set(sections.map((s) => s.nonconformity))], "cov");
  fillSelect("audit-epsilon", [...new Set(sections.map((s) => s.epsilon))], 0.1);
  drawAudit();
}

function fillSelect(id, values, preferred) {
  const select = document.getElementById(id);
  const current = select.value;
  select.replaceChildren(...values.map((v) => el("option", { value: v }, v)));
  const keep = values.map(String).includes(current) ? current : values.map(String).includes(String(preferred)) ? preferred : values[0];
  if (keep !== undefined) select.value = String(keep);
}

function drawAudit() {
  const report = state.audit?.report;
  const target = document.getElementById("audit-detail");
  if (!report) return target.replaceChildren();
  const kind = document.getElementById("audit-kind").value;
  const epsilon = Number(document.getElementById("audit-epsilon").value);
  const pick = (scope) => (report.sections || []).find((s) => s.nonconformity === kind && s.epsilon === epsilon && s.scope === scope);
  const keypointScope = pick("keypoint");
  const objectScope = pick("object");
  const verdict = report.passed ? el("span", { class: "pass" }, "passed") : el("span", { class: "fail" }, `${(report.flagged || []).length} figures flagged`);
  const nodes = [
    el("p", {}, `Audit #${state.audit.id} of version ${state.audit.version}, ${state.audit.instances} instances, `, verdict,
      ` (Holm over ${report.tests} tests, family-wise ${report.family_alpha}).`),
  ];
  if (keypointScope) {
    nodes.push(el("h3", {}, `Coverage per keypoint (${kind}, ε = ${epsilon}, keypoint scope) against its ${Math.round(100 * report.band_level)}% band`));
    nodes.push(coveragePlot(keypointScope.keypoints || [], 1 - epsilon));
    nodes.push(el("p", { class: "legend muted" }, "whiskers: the band a valid calibration gives;",
      el("span", { class: "dot ok" }), "inside", el("span", { class: "dot out" }), "outside the band",
      el("span", { class: "dot flagged" }), "significantly low (Holm); dashed: 1 − ε"));
    const overall = keypointScope.overall || {};
    nodes.push(note(`Overall ${fixed(overall.coverage)} on ${overall.m} keypoints, band ${fixed(overall.band?.[0])}–${fixed(overall.band?.[1])} (union bound).`));
  }
  if (objectScope) {
    // Folded like the drift's objects (open when one is flagged): a phone gets a page, not a card per object.
    const objects = objectScope.objects || [];
    const flagged = objects.filter((o) => o.flagged).length;
    const summary = el("summary", {}, el("strong", {}, "Per object"), ` (object scope: all keypoints of an instance at once): ${objects.length} objects, `,
      flagged ? el("span", { class: "fail" }, `${flagged} flagged`) : "none flagged");
    nodes.push(el("details", flagged ? { open: "" } : {}, summary, table(["object", "m", "coverage", "band", "p", "Holm p", ""], objects.map((o) => [
      o.object, o.m, fixed(o.coverage), `${fixed(o.band?.[0])}–${fixed(o.band?.[1])}`, fixed(o.p_value, 4),
      fixed(o.adjusted_p_value, 4), o.flagged ? el("span", { class: "fail" }, "flagged") : o.in_band ? "" : "outside band",
    ]))));
  }
  if (report.advice) nodes.push(el("details", {}, el("summary", {}, el("strong", {}, "What to do")), el("p", { class: "advice" }, report.advice)));
  target.replaceChildren(...nodes);
}

function coveragePlot(figures, promised) {
  const width = Math.max(640, 16 * figures.length + 60);
  const height = 240;
  const left = 44, right = 40, top = 10, bottom = 70;
  const values = figures.flatMap((f) => [f.coverage, ...(f.band || [])]).filter((v) => typeof v === "number");
  const low = Math.max(0, Math.floor(10 * Math.min(promised, ...values)) / 10);
  const y = (v) => top + (1 - (v - low) / (1 - low || 1)) * (height - top - bottom);
  const step = (width - left - right) / Math.max(1, figures.length);
  const x = (i) => left + step * (i + 0.5);
  const plot = svg("svg", { id: "audit-plot", width, height, viewBox: `0 0 ${width} ${height}`, role: "img",
    "aria-label": "coverage per keypoint with its band" });
  for (let tick = low; tick <= 1.0001; tick += (1 - low) / 5) {
    plot.append(svg("line", { class: "axis", x1: left, x2: width - right, y1: y(tick), y2: y(tick) }));
    plot.append(svg("text", { x: left - 4, y: y(tick) + 3, "text-anchor": "end" }, tick.toFixed(2)));
  }
  plot.append(svg("line", { class: "promised", x1: left, x2: width - right, y1: y(promised), y2: y(promised) }));
  figures.forEach((f, i) => {
    if (f.band) plot.append(svg("line", { class: "whisker", x1: x(i), x2: x(i), y1: y(f.band[0]), y2: y(f.band[1]) }));
    if (typeof f.coverage === "number") {
      const kind = f.flagged ? "coverage flagged" : f.in_band ? "coverage" : "coverage out";
      const point = svg("circle", { class: kind, cx: x(i), cy: y(f.coverage), r: 4, "data-keypoint": f.keypoint });
      point.append(svg("title", {}, `${f.keypoint}: ${fixed(f.coverage)} of ${f.m} (band ${fixed(f.band?.[0])}–${fixed(f.band?.[1])}, n ${f.n}, p ${fixed(f.p_value, 4)})`));
      plot.append(point);
    }
    const label = svg("text", { x: x(i), y: height - bottom + 8, transform: `rotate(60 ${x(i)} ${height - bottom + 8})` }, f.keypoint);
    plot.append(label);
  });
  return plot;
}

// ---------------------------------------------------------------- live coverage from field labels

const LIVE_LEVELS = ["version", "stratum", "stream", "group", "object", "keypoint"];

async function loadLiveCoverage() {
  state.live = await getJson("v1/admin/coverage/live");
  const groups = state.live.groups || [];
  if (!groups.length) {
    return onlyNote("live-coverage", 'No labelled feedback yet: predict with "retain": true, then POST the true points to /v1/feedback/{prediction_id} (docs/feedback.md).');
  }
  const alarms = groups.filter((g) => g.alarm).length;
  const verdict = alarms ? el("span", { class: "alarm" }, `Alarm raised in ${alarms} of ${groups.length} groups`) : `No alarm in ${groups.length} groups`;
  show("live-coverage", el("p", { class: "muted" },
    "Per calibration version and group: the labelled keypoints' coverage so far; an anytime-valid confidence sequence of the looks' mean ",
    "(a scene's frames vote once, together; valid however often it is read); the least coverage the version promises; ",
    `an alarm once coverage is proven below what the calibration gives (false-alarm probability ${state.live.alarm_level} per group). `, verdict, "."));
  const present = LIVE_LEVELS.filter((level) => groups.some((g) => g.level === level));
  const choices = [["summary", "totals and alarms"], ["all", "every group"], ...present.map((level) => [level, `per ${level}`])];
  const select = document.getElementById("live-level");
  const current = select.value || "summary";
  select.replaceChildren(...choices.map(([value, text]) => el("option", { value }, text)));
  select.value = choices.some(([value]) => value === current) ? current : "summary";
  document.querySelector("#live-coverage .controls").hidden = false;
  drawLiveCoverage();
}

function drawLiveCoverage() {
  const groups = state.live?.groups || [];
  const shown = document.getElementById("live-level").value;
  const wanted = (g) => shown === "all" || g.level === shown || (shown === "summary" && (g.level === "version" || g.alarm));
  const blocks = new Map();
  for (const g of groups.filter(wanted)) {
    const key = JSON.stringify([g.version, g.guarantee, g.nonconformity, g.coverage, g.epsilon, g.delta]);
    if (!blocks.has(key)) blocks.set(key, []);
    blocks.get(key).push(g);
  }
  const order = (g) => [g.alarm ? 0 : 1, LIVE_LEVELS.indexOf(g.level)];
  const nodes = [];
  for (const members of blocks.values()) {
    const g = members[0];
    const query = [`${g.nonconformity}, ${g.coverage} scope, ε = ${g.epsilon}`, g.delta === null ? "" : `, δ = ${g.delta}`,
      g.guarantee === "adaptive" ? ", adaptive sets (long-run bound: no floor, no alarm)" : ""].join("");
    nodes.push(el("h3", {}, `Version ${g.version}: ${query}`));
    members.sort((a, b) => { const [x, y] = [order(a), order(b)]; return x[0] - y[0] || x[1] - y[1] || a.name.localeCompare(b.name); });
    nodes.push(table(["group", "labelled", "covered so far", "looks", "look mean", "confidence sequence", "", "promised", "alarm"],
      members.map((m) => [
        m.level === "version" ? "all keypoints" : `${m.level}: ${m.name}`,
        m.labelled,
        fixed(m.labelled ? m.covered / m.labelled : null),
        m.looks,
        fixed(m.look_mean),
        el("span", { class: "nowrap interval-text" }, `${fixed(m.lower)}–${fixed(m.upper)}`),
        intervalPlot(m),
        m.guarantee === "adaptive" ? "long-run" : el("span", { class: "nowrap" }, `≥ ${fixed(m.floor)}`),
        m.alarm ? el("span", { class: "alarm" }, "alarm raised") : "no alarm",
      ])));
  }
  if (shown === "summary") nodes.push(note("Totals of each version and query, and every group whose alarm is raised; choose a level to see its groups."));
  document.getElementById("live-detail").replaceChildren(...nodes);
}

function intervalPlot(group) {
  // The confidence sequence on [0, 1]: a bar from lower to upper, the look mean a dot, the floor a tick, 1 − ε dashed.
  const width = 160, height = 18, x = (v) => 4 + v * (width - 8);
  const plot = svg("svg", { class: "live-interval", width, height, viewBox: `0 0 ${width} ${height}`,
    "data-level": group.level, "data-name": group.name });
  plot.append(svg("line", { class: "axis", x1: x(0), x2: x(1), y1: height / 2, y2: height / 2 }));
  plot.append(svg("line", { class: group.alarm ? "interval alarm" : "interval", x1: x(group.lower), x2: x(group.upper), y1: height / 2, y2: height / 2 }));
  if (group.guarantee !== "adaptive") plot.append(svg("line", { class: "floor", x1: x(group.floor), x2: x(group.floor), y1: 2, y2: height - 2 }));
  plot.append(svg("line", { class: "promised", x1: x(group.promised), x2: x(group.promised), y1: 2, y2: height - 2 }));
  if (typeof group.look_mean === "number") plot.append(svg("circle", { class: group.alarm ? "coverage flagged" : "coverage", cx: x(group.look_mean), cy: height / 2, r: 3 }));
  plot.append(svg("title", {}, `${group.level} ${group.name}: ${fixed(group.lower)}–${fixed(group.upper)}, look mean ${fixed(group.look_mean)}, floor ${fixed(group.floor)}, 1 − ε ${fixed(group.promised)}`));
  return plot;
}

// ---------------------------------------------------------------- drift and set sizes

async function driftAvailable() {
  // Ask the API document first, so that a server without drift monitoring is not asked for it.
  try {
    const document_ = await getJson("openapi.json", false);
    return Boolean(document_.paths && document_.paths["/v1/admin/drift"]);
  } catch (error) {
    return false;
  }
}

async function loadDrift() {
  let drift = null;
  if (await driftAvailable()) {
    try {
      drift = await getJson("v1/admin/drift");
    } catch (error) {
      if (!(error instanceof HttpError && error.status === 404)) throw error;
    }
  }
  if (!drift) {
    show("drift", note("No drift data: this server does not report drift yet."));
    show("set-sizes", note("Set sizes of recent predictions: not available."));
    return;
  }
  drawDrift(drift);
  drawSetSizes(drift.set_sizes);
}

function featureNames(keypoints) {
  return [...new Set(keypoints.flatMap((k) => Object.keys(k.features || {})))];
}

function drawDrift(drift) {
  const keypoints = Array.isArray(drift.keypoints) ? drift.keypoints : [];
  const features = featureNames(keypoints);
  const history = Array.isArray(drift.history) ? drift.history : [];
  const psi = drift.statistic === "psi";
  const alarmText = drift.alarm ? el("span", { class: "alarm" }, "alarm raised") : "no alarm";
  const method = drift.statistic === "sequential"
    ? `sequential test at level ${drift.alarm_threshold ?? "–"}: ${drift.independent_looks ?? 0} independent looks in ${drift.frames ?? 0} frames, evidence ${fixed(drift.evidence, 1)} of ${fixed(drift.evidence_threshold, 0)}; `
    : `${drift.statistic === "ks" ? "Kolmogorov-Smirnov, Holm-corrected at" : "PSI, alarm above"} ${drift.alarm_threshold ?? "–"}; `;
  const header = el("p", { class: "muted" }, method,
    `window ${drift.window ?? "–"} live instances per keypoint; reference: version ${drift.reference_version ?? "–"}; `,
    `${drift.recorded ?? 0} live values recorded; `, alarmText, ".");
  const nodes = [header];
  if (drift.reference_available === false && drift.reason) nodes.push(note(drift.reason));
  if (!keypoints.length) return show("drift", ...nodes, note("No drift data yet."));
  const cells = (k) => [
    k.keypoint ?? "",
    ...features.map((name) => {
      const feature = (k.features || {})[name] || {};
      // Each number whole: the statistic and its "(p 0.903)" wrap between, never inside.
      const parts = [el("span", { class: "nowrap" }, fixed(feature.statistic))];
      if (typeof feature.p_value === "number") parts.push(" ", el("span", { class: "nowrap" }, `(p ${fixed(feature.p_value, 3)})`));
      if (feature.alarm) parts.push(" alarm");
      return el("span", feature.alarm ? { class: "alarm" } : {}, ...parts);
    }),
    sparkline(historyOf(history, k), psi ? drift.alarm_threshold : undefined, alarmed(k)),
  ];
  const span = history.length > 1 ? ` (${history.length} points, ${when(new Date(1000 * history[0].time).toISOString())} to now)` : "";
  nodes.push(note(`Per object, its keypoints behind it (an object with an alarm is open). Over time: each keypoint's largest statistic${span}.`));
  // One block per object, its keypoints' rows folded behind it: a phone gets a page, not a card per keypoint.
  for (const [object, members] of byObject(keypoints)) {
    const raised = members.filter(alarmed).length;
    const largest = Math.max(...members.flatMap((k) => Object.values(k.features || {}).map((f) => f?.statistic)).filter((v) => typeof v === "number"));
    const verdict = raised ? el("span", { class: "alarm" }, `alarm on ${raised}`) : "no alarm";
    const summary = el("summary", {}, el("strong", {}, object), ` ${members.length} keypoints, largest statistic ${fixed(largest)}, `, verdict);
    nodes.push(el("details", raised ? { class: "object", open: "" } : { class: "object" }, summary,
      table(["keypoint", ...features, "over time"], members.map(cells))));
  }
  show("drift", ...nodes);
}

function alarmed(keypoint) {
  return Object.values(keypoint.features || {}).some((f) => f?.alarm);
}

function byObject(keypoints) {
  const groups = new Map();
  for (const k of keypoints) {
    const object = k.object ?? "";
    if (!groups.has(object)) groups.set(object, []);
    groups.get(object).push(k);
  }
  return groups;
}

function historyOf(history, keypoint) {
  // One value per past window: the largest statistic of this keypoint's features.
  return history.map((point) => {
    if (Array.isArray(point?.keypoint_statistics)) {
      const value = point.keypoint_statistics[keypoint.index];
      return typeof value === "number" ? value : null;
    }
    const entries = Array.isArray(point?.keypoints) ? point.keypoints : [];
    const match = entries.find((e) => e.index === keypoint.index);
    const statistics = Object.values(match?.features || {}).map((f) => f?.statistic).filter((v) => typeof v === "number");
    return statistics.length ? Math.max(...statistics) : null;
  });
}

function sparkline(values, threshold, alarm) {
  const width = 160, height = 28;
  const known = values.filter((v) => typeof v === "number");
  if (!known.length) return "–";
  const top = Math.max(...known, typeof threshold === "number" ? threshold : 0) || 1;
  const x = (i) => (values.length < 2 ? width / 2 : (i * (width - 4)) / (values.length - 1) + 2);
  const y = (v) => height - 2 - (v / top) * (height - 4);
  const line = svg("svg", { class: "sparkline", width, height, viewBox: `0 0 ${width} ${height}` });
  if (typeof threshold === "number") line.append(svg("line", { class: "threshold", x1: 0, x2: width, y1: y(threshold), y2: y(threshold) }));
  const points = values.map((v, i) => (typeof v === "number" ? `${x(i)},${y(v)}` : null)).filter(Boolean);
  if (points.length === 1) line.append(svg("circle", { class: "bar", cx: points[0].split(",")[0], cy: points[0].split(",")[1], r: 2 }));
  line.append(svg("polyline", { class: alarm ? "series alarm" : "series", points: points.join(" ") }));
  return line;
}

function histogramOf(sizes) {
  // {histogram_edges, histogram_counts} (the drift endpoint's), {edges|bins, counts}, or a list of sizes.
  if (!sizes) return null;
  if (Array.isArray(sizes)) {
    const values = sizes.filter((v) => typeof v === "number" && Number.isFinite(v));
    if (!values.length) return null;
    const low = Math.min(...values), high = Math.max(...values);
    const bins = 20, width = (high - low) / bins || 1;
    const counts = new Array(bins).fill(0);
    values.forEach((v) => { counts[Math.min(bins - 1, Math.floor((v - low) / width))] += 1; });
    return { edges: counts.map((_, i) => low + i * width).concat(high), counts };
  }
  const counts = sizes.histogram_counts || sizes.counts;
  const edges = sizes.histogram_edges || sizes.edges || sizes.bins;
  if (Array.isArray(counts) && Array.isArray(edges) && edges.length === counts.length + 1) return { edges, counts };
  return null;
}

function drawSetSizes(sizes) {
  const kinds = sizes && typeof sizes === "object" && !Array.isArray(sizes) ? Object.entries(sizes) : [];
  const nodes = [];
  for (const [kind, value] of kinds) {
    const summary = value?.semi_major_px ?? value;
    const histogram = histogramOf(summary);
    if (!histogram) continue;
    const quantiles = summary.quantiles ? Object.entries(summary.quantiles).map(([q, v]) => `${q} ${fixed(v, 1)}`).join(", ") : "";
    const counts = typeof value?.n === "number" ? `${value.n} sets, ${value.unbounded ?? 0} unbounded` : "";
    // Each kind's figures in one line, its histogram behind it: the page stays short on a phone.
    const title = el("summary", {}, el("strong", {}, kind), `: semi-major axis (px); ${[counts, quantiles].filter(Boolean).join("; ")}`);
    nodes.push(el("details", { class: "kind" }, title, histogramPlot(histogram, kind)));
  }
  if (!nodes.length) return show("set-sizes", note("Set sizes of recent predictions: not available (no recent prediction)."));
  show("set-sizes", ...nodes);
}

function histogramPlot({ edges, counts }, kind) {
  const width = 520, height = 140, left = 36, bottom = 24, top = 8;
  const most = Math.max(1, ...counts);
  const barWidth = (width - left - 8) / Math.max(1, counts.length);
  const plot = svg("svg", { class: "histogram", width, height, viewBox: `0 0 ${width} ${height}`, "data-kind": kind });
  counts.forEach((count, i) => {
    const barHeight = (count / most) * (height - top - bottom);
    const bar = svg("rect", { class: "bar", x: left + i * barWidth + 1, y: height - bottom - barHeight, width: Math.max(1, barWidth - 2), height: barHeight });
    bar.append(svg("title", {}, `${fixed(edges[i], 1)}–${fixed(edges[i + 1], 1)} px: ${count}`));
    plot.append(bar);
  });
  plot.append(svg("text", { x: left, y: height - 8 }, fixed(edges[0], 1)));
  plot.append(svg("text", { x: width - 8, y: height - 8, "text-anchor": "end" }, fixed(edges[edges.length - 1], 1)));
  plot.append(svg("text", { x: left - 4, y: top + 8, "text-anchor": "end" }, most));
  return plot;
}

// ---------------------------------------------------------------- wiring

const ADMIN_PANELS = {
  versions: loadVersions, activations: loadActivations, audits: loadAudits, "live-coverage": loadLiveCoverage, drift: loadDrift,
};

async function loadAdmin() {
  const status = document.getElementById("token-state");
  if (!state.token) {
    status.textContent = "no token";
    for (const id of [...Object.keys(ADMIN_PANELS), "set-sizes"]) onlyNote(id, "Enter the admin token above to see this.");
    return;
  }
  status.textContent = "token in use (this tab only)";
  await Promise.all(Object.entries(ADMIN_PANELS).map(async ([id, load]) => {
    try {
      await load();
    } catch (error) {
      show(id, failure(error));
    }
  }));
  document.body.dataset.loaded = "true";
}

function wire() {
  const input = document.getElementById("token");
  input.value = state.token;
  document.getElementById("token-form").addEventListener("submit", (event) => {
    event.preventDefault();
    state.token = input.value.trim();
    if (state.token) sessionStorage.setItem(TOKEN_KEY, state.token);
    else sessionStorage.removeItem(TOKEN_KEY);
    loadAdmin();
  });
  document.getElementById("forget").addEventListener("click", () => {
    state.token = "";
    input.value = "";
    sessionStorage.removeItem(TOKEN_KEY);
    delete document.body.dataset.loaded;
    loadAdmin();
  });
  document.getElementById("audit-choice").addEventListener("change", (event) => {
    loadAudit(event.target.value).catch((error) => document.getElementById("audit-detail").replaceChildren(failure(error)));
  });
  for (const id of ["audit-kind", "audit-epsilon"]) document.getElementById(id).addEventListener("change", drawAudit);
  document.getElementById("live-level").addEventListener("change", drawLiveCoverage);
}

wire();
loadModel().then(loadAdmin);

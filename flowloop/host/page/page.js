// flowloop live page: grip, flow and temperature as they happen, the active
// profile's lines and the printed file's plan, from Moonraker's websocket.
//
// Memory is bounded: updates only change the held status; the timeline
// samples it every SAMPLE_MS into a ring of SAMPLES, the event list holds
// EVENTS entries, a plan or a profile replaces the last one.
/* global uPlot */
(function () {
  "use strict";

  const WINDOW_S = 300;          // the timeline shows the last five minutes
  const SAMPLE_MS = 250;         // klippy's own status period
  // One sample per SAMPLE_MS whatever the update rate: WINDOW_S of them.
  const SAMPLES = WINDOW_S * 1000 / SAMPLE_MS;
  const EVENTS = 50;
  const REDRAW_MS = 500;
  const RECONNECT_MS = 2000;
  const REPORT_DELAY_MS = 2000;
  // A steady hotend wanders by a tenth of a degree: the temperature axes
  // span at least this much, so noise does not read as steps.
  const TEMP_MIN_SPAN_C = 10;

  // The colours of flowloop's plots: live_page.document() writes
  // flowloop.material.plot.COLORS in place of this mark when it serves the page.
  const COLORS = {/* plot.COLORS */};

  const query = new URLSearchParams(location.search);
  // ?extruder= shows one tool; without it the page follows the tool that
  // prints (toolhead.extruder), as ACTIVATE_EXTRUDER and T0/T1 change it.
  const chosen = query.get("extruder");
  // ?panel=1: laid out for a dashboard panel of Mainsail or Fluidd (page.css)
  const panel = query.get("panel") === "1";
  if (panel) document.documentElement.dataset.panel = "true";
  const CHART_HEIGHT = panel ? 150 : 220;
  let extruder = chosen || "extruder";
  // Moonraker may sit behind a proxy under a prefix: everything is asked
  // relative to where the page was served from.
  const base = location.pathname.replace(/server\/flowloop\/page\/?$/, "");

  // --- authorization, the way Mainsail does it ------------------------------
  // A JSON web token in the URL (?access_token=, what Moonraker's
  // /access/login hands out) or an API key in the URL's fragment
  // (#api_key=..., kept in localStorage; a fragment never reaches a server
  // log) authorise the request for a oneshot token; a trusted client needs
  // neither. The websocket then opens with that token.
  function apiKey() {
    const hash = new URLSearchParams(location.hash.slice(1));
    const key = hash.get("api_key");
    if (key) {
      try { localStorage.setItem("flowloop.api_key", key); } catch (e) { /* private mode */ }
      history.replaceState(null, "", location.pathname + location.search);
      return key;
    }
    try { return localStorage.getItem("flowloop.api_key"); } catch (e) { return null; }
  }

  function authHeaders() {
    const headers = {};
    const jwt = query.get("access_token");
    const key = apiKey();
    if (jwt) headers.Authorization = "Bearer " + jwt;
    else if (key) headers["X-Api-Key"] = key;
    return headers;
  }

  async function oneshotToken() {
    const resp = await fetch(base + "access/oneshot_token", {headers: authHeaders(),
                                                             cache: "no-store"});
    if (resp.status === 401 || resp.status === 403) {
      const err = new Error("Moonraker asks for authorization and this browser has " +
        "none: open the page from a trusted client (moonraker.conf [authorization] " +
        "trusted_clients), with ?access_token=<token from /access/login>, or with " +
        "#api_key=<Moonraker's API key> at the end of its address.");
      err.refused = true;
      throw err;
    }
    if (resp.status === 404) return null;  // no [authorization]: nothing to ask
    if (!resp.ok) throw new Error("oneshot token: HTTP " + resp.status);
    return (await resp.json()).result;
  }

  // --- small DOM helpers ------------------------------------------------------
  const $ = (sel) => document.querySelector(sel);

  function setConnection(state, text) {
    const el = $("#connection");
    el.dataset.state = state;
    el.textContent = text;
  }

  function notice(text) {
    const el = $("#notice");
    el.hidden = !text;
    el.textContent = text || "";
  }

  // The message of a chart: where the chart would be, in words.
  function say(chartId, text) {
    const chart = document.getElementById(chartId);
    const msg = chart.previousElementSibling;
    msg.hidden = !text;
    msg.textContent = text || "";
    chart.hidden = !!text;
    chart.dataset.message = text || "";
  }

  function sayAll(text) {
    for (const id of ["flow-chart", "temp-chart", "profile-chart", "plan-chart"]) {
      say(id, text);
    }
    const events = $("#now .message");
    events.hidden = !text;
    events.textContent = text || "";
  }

  function fmt(value, digits) {
    if (value === null || value === undefined) return "–";
    if (typeof value === "number") return value.toFixed(digits);
    return String(value);
  }

  function setField(field, value, digits) {
    const cell = document.querySelector(`td[data-field="${field}"]`);
    cell.textContent = fmt(value, digits);
    cell.dataset.value = value === null || value === undefined ? "" : String(value);
  }

  // --- the websocket: JSON-RPC with notifications -------------------------
  class Rpc {
    constructor(url, onNotify, onClose) {
      this.nextId = 0;
      this.pending = new Map();
      this.ws = new WebSocket(url);
      this.ws.onmessage = (ev) => this.receive(JSON.parse(ev.data), onNotify);
      this.ws.onclose = () => {
        for (const {reject} of this.pending.values()) reject(new Error("closed"));
        this.pending.clear();
        onClose();
      };
      this.opened = new Promise((resolve, reject) => {
        this.ws.onopen = resolve;
        this.ws.onerror = () => reject(new Error("websocket error"));
      });
    }

    receive(msg, onNotify) {
      if (msg.id !== undefined && this.pending.has(msg.id)) {
        const {resolve, reject} = this.pending.get(msg.id);
        this.pending.delete(msg.id);
        if (msg.error) {
          const err = new Error(msg.error.message);
          err.code = msg.error.code;
          reject(err);
        } else {
          resolve(msg.result);
        }
      } else if (msg.method) {
        onNotify(msg.method, msg.params || []);
      }
    }

    call(method, params) {
      const id = ++this.nextId;
      return new Promise((resolve, reject) => {
        this.pending.set(id, {resolve, reject});
        this.ws.send(JSON.stringify({jsonrpc: "2.0", method, params: params || {}, id}));
      });
    }

    close() { this.ws.close(); }
  }

  // --- the timeline: a ring of samples ------------------------------------
  const FIELDS = ["time", "commanded", "measured", "cap", "planned", "grip",
                  "temperature", "target"];

  class Ring {
    constructor(size) {
      this.size = size;
      this.count = 0;
      this.next = 0;
      this.columns = FIELDS.map(() => new Float64Array(size));
    }

    push(values) {
      FIELDS.forEach((name, i) => {
        const v = values[name];
        this.columns[i][this.next] = typeof v === "number" ? v : NaN;
      });
      this.next = (this.next + 1) % this.size;
      this.count = Math.min(this.count + 1, this.size);
    }

    // uPlot's data: oldest first, null where nothing was known.
    data() {
      const start = (this.next - this.count + this.size) % this.size;
      return this.columns.map((col) => {
        const out = new Array(this.count);
        for (let k = 0; k < this.count; k++) {
          const v = col[(start + k) % this.size];
          out[k] = Number.isNaN(v) ? null : v;
        }
        return out;
      });
    }
  }

  // --- state ------------------------------------------------------------
  let rpc = null;
  let status = {};           // printer object -> its fields, as subscribed
  let names = {};            // sensor, limiter, autotemp object names for `extruder`
  let tools = {};            // every extruder -> its sensor, limiter, autotemp names
  let ring = new Ring(SAMPLES);
  let charts = {};
  let lines = null;          // the active profile's lines (server.flowloop.page.lines)
  let plan = null;           // the printed file's plan (server.flowloop.page.plan)
  let planFile = null;
  let profileKey = null;
  let lastFault = null;
  let lastErrors = null;     // null: the first counts are not news
  let redrawTimer = null;

  function width(el) {
    return Math.max(panel ? 200 : 300, el.parentElement.clientWidth - 8);
  }

  // Axes in the page's text colour: light or dark as the browser prefers
  // (page.css), redrawn when that preference changes.
  const dark = window.matchMedia("(prefers-color-scheme: dark)");
  function themed(axes) {
    const text = getComputedStyle(document.body).color;
    const line = {stroke: "#8884", width: 1};
    return (axes || []).map((a) => Object.assign({stroke: text, grid: line, ticks: line},
      a, {grid: Object.assign({}, line, a.grid)}));
  }

  const chartOpts = {};
  function makeChart(id, opts, data) {
    const el = document.getElementById(id);
    if (charts[id]) charts[id].destroy();
    chartOpts[id] = opts;
    charts[id] = new uPlot(Object.assign({width: width(el), height: CHART_HEIGHT}, opts,
      {axes: themed(opts.axes)}), data, el);
    showNow(charts[id]);
    return charts[id];
  }
  dark.addEventListener("change", () => {
    for (const [id, chart] of Object.entries(charts)) makeChart(id, chartOpts[id], chart.data);
  });

  // Centred on the data, at least TEMP_MIN_SPAN_C wide.
  function tempRange(u, lo, hi) {
    if (typeof lo !== "number" || typeof hi !== "number") return [0, TEMP_MIN_SPAN_C];
    const half = Math.max(TEMP_MIN_SPAN_C, (hi - lo) * 1.1) / 2;
    return [(lo + hi) / 2 - half, (lo + hi) / 2 + half];
  }

  // The y range a chart shows, for whoever reads the page's state.
  const publishRange = (scale) => (u, key) => {
    if (key === scale) {
      u.root.parentElement.dataset.yRange = u.scales[key].min + "," + u.scales[key].max;
    }
  };

  // uPlot's legend shows the hovered values, and "--" off the chart. Off the
  // chart ours shows the values now: nowIdx(u, series) is the data index of
  // "now" (the latest sample, the hotend's temperature, the print's position).
  function legendValue(nowIdx, format) {
    return (u, v, si, di) => {
      if (di === null || di === undefined) {
        const k = nowIdx(u, si);
        v = k === null ? null : u.data[si][k];
      }
      return v === null || v === undefined ? "–" : format(v);
    };
  }

  const digits = (n) => (v) => v.toFixed(n);
  const clock = (t) => new Date(t * 1000).toLocaleTimeString();

  function latestIdx(u, si) {
    const d = u.data[si] || [];
    for (let k = d.length - 1; k >= 0; k--) if (d[k] !== null) return k;
    return null;
  }

  function idxOf(value) {
    return (u) => {
      const v = value();
      const xs = u.data[0] || [];
      if (typeof v !== "number" || !xs.length || v < xs[0] || v > xs[xs.length - 1]) {
        return null;
      }
      return u.valToIdx(v);
    };
  }

  // After new data: the legend shows now, unless the cursor is on the chart.
  function showNow(chart) {
    if (chart.cursor.idx === null || chart.cursor.idx === undefined) {
      chart.setLegend({idx: null});
    }
  }

  function timelineCharts() {
    const data = ring.data();
    const flowData = [data[0], data[1], data[2], data[3], data[4], data[5]];
    const tempData = [data[0], data[6], data[7]];
    const latest = (n) => legendValue(latestIdx, digits(n));
    const time = {value: legendValue(latestIdx, clock)};
    const flow = {
      scales: {x: {time: true}, flow: {range: (u, lo, hi) => [0, Math.max(1, hi * 1.1)]},
               grip: {range: [0, 1.2]}},
      axes: [{}, {scale: "flow", label: "mm³/s"},
             {scale: "grip", side: 1, label: "grip", grid: {show: false}}],
      series: [time,
        {label: "commanded", scale: "flow", stroke: COLORS.demand, width: 1.5,
         value: latest(2)},
        {label: "measured", scale: "flow", stroke: COLORS.measured, width: 1.5,
         value: latest(2)},
        {label: "limiter cap", scale: "flow", stroke: COLORS.cap, width: 1.5, dash: [6, 4],
         value: latest(2)},
        {label: "autotemp flow", scale: "flow", stroke: COLORS.planned, width: 1.5,
         dash: [2, 3], value: latest(2)},
        {label: "grip", scale: "grip", stroke: COLORS.grip, width: 1.5, value: latest(3)}],
    };
    const temp = {
      scales: {x: {time: true}, y: {range: tempRange}},
      axes: [{}, {label: "°C"}],
      series: [time,
        {label: "temperature", stroke: COLORS.nozzle, width: 1.5, value: latest(1)},
        {label: "target", stroke: COLORS.target, width: 1.5, dash: [6, 4],
         value: latest(1)}],
      hooks: {setScale: [publishRange("y")]},
    };
    if (!charts["flow-chart"]) makeChart("flow-chart", flow, flowData);
    if (!charts["temp-chart"]) makeChart("temp-chart", temp, tempData);
    const now = Date.now() / 1000;
    // from the oldest sample (at least the last 30 s) to now: a page opened
    // a minute ago shows its minute across the chart
    const oldest = data[0].length ? data[0][0] : now;
    const from = Math.min(now - 30, Math.max(now - WINDOW_S, oldest));
    for (const [id, d] of [["flow-chart", flowData], ["temp-chart", tempData]]) {
      const chart = charts[id];
      chart.batch(() => {
        chart.setData(d, false);
        chart.setScale("x", {min: from, max: now});
      });
      showNow(chart);
      chart.root.parentElement.dataset.samples = String(ring.count);
    }
  }

  // The live operating point on the profile's lines: flow against temperature.
  function livePoint() {
    const heater = status[extruder] || {};
    const sensor = names.sensor ? status[names.sensor] || {} : {};
    const flow = typeof sensor.measured_flow === "number" ? sensor.measured_flow
      : sensor.commanded_flow;
    return {temp: heater.temperature, flow};
  }

  const atTemp = idxOf(() => livePoint().temp);

  function profileChart() {
    if (!lines) return;
    const point = {
      hooks: {draw: [(u) => {
        const p = livePoint();
        if (typeof p.temp !== "number" || typeof p.flow !== "number") return;
        const x = u.valToPos(p.temp, "x", true);
        const y = u.valToPos(p.flow, "y", true);
        const ctx = u.ctx;
        ctx.save();
        ctx.beginPath();
        ctx.arc(x, y, 6 * devicePixelRatio, 0, 2 * Math.PI);
        ctx.fillStyle = COLORS.now;
        ctx.fill();
        ctx.restore();
      }]},
    };
    const opts = Object.assign({
      scales: {x: {time: false}, y: {range: (u, lo, hi) => [0, Math.max(1, hi * 1.1)]}},
      axes: [{label: "hotend °C"}, {label: "mm³/s"}],
      // off the chart: the lines at the hotend's temperature now
      series: [{label: "°C", value: legendValue(atTemp, digits(1))},
        {label: "into air", stroke: COLORS.into_air, width: 1.5, points: {show: false},
         value: legendValue(atTemp, digits(2))},
        {label: "real print", stroke: COLORS.real_print, width: 1.5,
         points: {show: false}, value: legendValue(atTemp, digits(2))},
        {label: "working point " + lines.working_point, stroke: COLORS.working, width: 2,
         dash: [8, 4], points: {show: false}, value: legendValue(atTemp, digits(2))}],
    }, point);
    makeChart("profile-chart", opts,
              [lines.temp_c, lines.into_air, lines.real_print, lines.working]);
    $("#profile-name").textContent = lines.name + " at working point " + lines.working_point;
  }

  // The print time of the file position: linear between the two
  // announcements (or the file's end) around it.
  function planPosition() {
    const sd = status.virtual_sdcard || {};
    const pos = plan && plan.positions;
    if (!pos || !pos.length || typeof sd.file_position !== "number") return null;
    if (sd.file_position <= pos[0][0]) return pos[0][1];
    let lo = 0;
    let hi = pos.length - 1;
    while (lo < hi) {  // the last entry at or before the position
      const mid = (lo + hi + 1) >> 1;
      if (pos[mid][0] <= sd.file_position) lo = mid; else hi = mid - 1;
    }
    if (lo === pos.length - 1) return pos[lo][1];
    const [o0, t0] = pos[lo];
    const [o1, t1] = pos[lo + 1];
    return t0 + (t1 - t0) * (sd.file_position - o0) / Math.max(1, o1 - o0);
  }

  const atPosition = idxOf(planPosition);

  function planChart() {
    const marker = {
      hooks: {draw: [(u) => {
        const t = planPosition();
        document.getElementById("plan-chart").dataset.position = t === null ? "" : String(t);
        if (t === null) return;
        const x = u.valToPos(t, "x", true);
        const ctx = u.ctx;
        ctx.save();
        ctx.strokeStyle = COLORS.now;
        ctx.lineWidth = 2 * devicePixelRatio;
        ctx.beginPath();
        ctx.moveTo(x, u.bbox.top);
        ctx.lineTo(x, u.bbox.top + u.bbox.height);
        ctx.stroke();
        ctx.restore();
      }]},
    };
    const opts = Object.assign({
      scales: {x: {time: false}, flow: {range: (u, lo, hi) => [0, Math.max(1, hi * 1.1)]},
               temp: {range: tempRange}},
      axes: [{label: "print time, s"}, {scale: "flow", label: "mm³/s"},
             {scale: "temp", side: 1, label: "°C", grid: {show: false}}],
      // off the chart: the plan where the print is now
      series: [{label: "s", value: legendValue(atPosition, digits(0))},
        {label: "announced flow", scale: "flow", stroke: COLORS.planned, width: 1.5,
         value: legendValue(atPosition, digits(2))},
        {label: "autotemp target", scale: "temp", stroke: COLORS.target, width: 1.5,
         value: legendValue(atPosition, digits(0))}],
    }, marker);
    makeChart("plan-chart", opts, [plan.time_s, plan.flow_mm3_s, plan.target_c]);
    $("#plan-name").textContent = plan.file + ", " + Math.round(plan.print_time_s) +
      " s of print time";
  }

  // --- what arrives -----------------------------------------------------
  function merge(diff) {
    for (const [name, fields] of Object.entries(diff || {})) {
      status[name] = Object.assign(status[name] || {}, fields);
    }
  }

  function parts() {
    return {
      heater: status[extruder] || {},
      sensor: names.sensor ? status[names.sensor] || {} : {},
      limiter: names.limiter ? status[names.limiter] || {} : {},
      autotemp: names.autotemp ? status[names.autotemp] || {} : {},
    };
  }

  function sample() {
    if (!names.ready) return;
    const {heater, sensor, limiter, autotemp} = parts();
    ring.push({time: Date.now() / 1000, commanded: sensor.commanded_flow,
               measured: sensor.measured_flow, grip: sensor.grip,
               cap: limiter.enabled ? limiter.cap : null,
               planned: autotemp.planned_flow,
               temperature: heater.temperature, target: heater.target});
    scheduleRedraw();
  }

  function readout() {
    const {heater, sensor, limiter, autotemp} = parts();
    setField("commanded_flow", sensor.commanded_flow, 2);
    setField("measured_flow", sensor.measured_flow, 2);
    setField("grip", sensor.grip, 3);
    setField("temperature", heater.temperature, 1);
    setField("target", heater.target, 1);
    setField("cap", names.limiter ? limiter.cap : null, 2);
    setField("reason", names.limiter ? (limiter.enabled ? limiter.reason : "off") : null);
    setField("planned_flow", names.autotemp ? autotemp.planned_flow : null, 2);
    setField("source", names.autotemp ? autotemp.source : null);
    setField("fault", names.sensor ? sensor.fault : null);
    // the sensor's error counts hold only the kinds seen so far
    const errors = names.sensor ? sensor.errors || {} : null;
    setField("time_lost", errors ? errors.time_lost || 0 : null, 0);
    if (errors) events(sensor.fault, errors);
  }

  function addEvent(text) {
    const list = $("#events");
    $("#now .message").hidden = true;
    const item = document.createElement("li");
    item.textContent = new Date().toLocaleTimeString() + " " + text;
    list.prepend(item);
    while (list.children.length > EVENTS) list.lastElementChild.remove();
  }

  // Faults as they start and end, and every kind of error as its count grows
  // (time_lost: reads the MCU could not time, see flow_sensor.md).
  function events(fault, errors) {
    const sensor = names.sensor.replace(/^flow_sensor /, "");
    if (fault !== lastFault) {
      if (fault) addEvent(`sensor ${sensor}: fault (${fault})`);
      else if (lastFault) addEvent(`sensor ${sensor}: fault cleared`);
      lastFault = fault;
    }
    for (const [kind, count] of Object.entries(errors)) {
      const before = lastErrors === null ? count : lastErrors[kind] || 0;
      if (count > before) {
        addEvent(`sensor ${sensor}: ${count - before} more ${kind} ` +
                 `(${count} since start)`);
      }
    }
    lastErrors = Object.assign({}, errors);
  }

  function scheduleRedraw() {
    if (redrawTimer !== null) return;
    redrawTimer = setTimeout(() => {
      redrawTimer = null;
      if (names.ready) {
        timelineCharts();
        for (const id of ["profile-chart", "plan-chart"]) {
          if (!charts[id]) continue;
          charts[id].redraw(false, false);
          showNow(charts[id]);
        }
      }
    }, REDRAW_MS);
  }

  async function refreshLines() {
    const key = JSON.stringify((status.flowloop || {}).profiles || {});
    if (key === profileKey) return;
    profileKey = key;
    const answer = await rpc.call("server.flowloop.page.lines", {extruder});
    lines = answer.lines;
    if (!lines) {
      say("profile-chart", `No active profile for ${extruder}: activate one ` +
          "(flowloop profile activate, or POST /server/flowloop/profile/activate) " +
          "to see its lines and where the hotend runs on them.");
      $("#profile-name").textContent = "";
      return;
    }
    say("profile-chart", null);
    profileChart();
  }

  async function refreshPlan(force) {
    const stats = status.print_stats || {};
    const file = stats.filename || null;
    if (file === planFile && !force) return;
    planFile = file;
    plan = null;
    $("#plan-name").textContent = file || "";
    if (!file) {
      say("plan-chart", "No file is being printed: the plan of an annotated file " +
          "shows here while it prints.");
      return;
    }
    say("plan-chart", `Reading ${file}...`);
    const answer = await rpc.call("server.flowloop.page.plan", {extruder, filename: file});
    if (file !== planFile) return;  // another file started meanwhile
    if (!answer.annotated) {
      say("plan-chart", answer.why);
      return;
    }
    plan = answer;
    say("plan-chart", null);
    planChart();
    if (answer.why) $("#plan-name").textContent += " (no temperature: " + answer.why + ")";
  }

  function onStatus(diff) {
    merge(diff);
    if (!names.ready) return;
    const printing = (diff.toolhead || {}).extruder;
    if (!chosen && printing && printing !== extruder) {
      extruder = printing;     // a tool change: the page follows it
      start().catch(fail);
      return;
    }
    readout();
    toolsTable();
    if (diff.flowloop) refreshLines().catch(fail);
    if (diff.print_stats && "filename" in diff.print_stats) refreshPlan().catch(fail);
  }

  // --- which objects belong to an extruder ---------------------------------
  // [flowrate_limiter extruder1] is extruder1's; the plain section is its
  // `extruder` option's (default extruder), as for [autotemp].
  function choose(objects, settings, tool) {
    const ofExtruder = (section) => ((settings[section] || {}).extruder || "extruder") === tool;
    const sensors = objects.filter((o) => o.startsWith("flow_sensor ") && ofExtruder(o));
    const section = (kind) => objects.includes(kind + " " + tool) ? kind + " " + tool
      : objects.includes(kind) && ofExtruder(kind) ? kind : null;
    return {
      sensor: sensors.length ? sensors[0] : null,
      limiter: section("flowrate_limiter"),
      autotemp: section("autotemp"),
    };
  }

  // One row per tool: what each tool's sensor, limiter and autotemp say now.
  function toolsTable() {
    const body = $("#tools tbody");
    const printing = (status.toolhead || {}).extruder;
    const profiles = (status.flowloop || {}).profiles || {};
    body.textContent = "";
    for (const [tool, own] of Object.entries(tools)) {
      const of = (obj) => (obj ? status[obj] || {} : {});
      const limiter = of(own.limiter);
      const cap = !own.limiter ? "no limiter" : !limiter.enabled ? "off"
        : fmt(limiter.cap, 2) + " (" + limiter.reason + ")";
      const cells = [tool + (tool === printing ? " (printing)" : ""),
        own.sensor ? fmt(of(own.sensor).grip, 3) : "no sensor", cap,
        own.autotemp ? fmt(of(own.autotemp).target, 1) : "no autotemp",
        fmt(of(tool).target, 1), (profiles[tool] || {}).name || "none"];
      const row = document.createElement("tr");
      row.dataset.tool = tool;
      for (const text of cells) {
        const td = document.createElement("td");
        td.textContent = text;
        row.append(td);
      }
      body.append(row);
    }
  }

  function extruderLinks(extruders) {
    const nav = $("#extruders");
    nav.textContent = "";
    for (const name of extruders) {
      const a = document.createElement("a");
      a.textContent = name;
      a.href = "?extruder=" + encodeURIComponent(name) + location.hash;
      if (name === extruder) a.setAttribute("aria-current", "page");
      nav.append(a);
    }
  }

  function link(text, href) {
    const a = document.createElement("a");
    a.textContent = text;
    a.href = href;
    // in a dashboard panel: a new tab, not the panel's small frame
    if (panel) { a.target = "_blank"; a.rel = "noopener"; }
    return a;
  }

  function listIn(id, items, none) {
    const list = $("#" + id);
    const message = list.previousElementSibling;
    list.textContent = "";
    message.hidden = items.length > 0;
    message.textContent = none;
    for (const parts of items) {
      const li = document.createElement("li");
      li.append(...parts);
      list.append(li);
    }
  }

  // Each job's flow report and each profile's nozzle health, linked to what
  // Moonraker serves (flow_report.md, nozzle_health.md)
  async function refreshReports() {
    const answer = await rpc.call("server.flowloop.reports");
    listIn("report-list", answer.reports.slice(0, 5).map((r) => r.problem
      ? [`job ${r.job_id}: ${r.problem}`]
      : [link(`job ${r.job_id}: ${r.filename || "no file"}`,
              `${base}server/flowloop/report?job_id=${encodeURIComponent(r.job_id)}`),
         ` ${r.state || "running"}, under-extruded ${fmt(r.under_extruded_mm, 2)} mm,` +
         ` slowed ${fmt(r.slowed_s, 1)} s`]),
      "No report yet: one is stored when a job of Moonraker's history ends.");
    const health = await rpc.call("server.flowloop.get_nozzle_health");
    listIn("health-list", health.histories.map((h) => {
      const last = h.prints[h.prints.length - 1] || {};
      const state = h.verdict && h.verdict.warn ? "WARNING: " + h.verdict.text
        : last.ratio != null ? `melt capacity ${fmt(100 * last.ratio, 0)} % of the profile`
          : "no estimate yet" + (last.reason ? ` (${last.reason})` : "");
      return [link(`${h.profile} on ${h.hotend}`,
                   `${base}server/flowloop/nozzle_health/plot?profile=` +
                   encodeURIComponent(h.profile)),
              `: ${state}, ${h.prints.length} print(s)`];
    }), "No print judged yet: each job with an active profile is.");
    $("#health-list").dataset.warn = String(
      health.histories.some((h) => h.verdict && h.verdict.warn));
  }

  async function start() {
    refreshReports().catch(fail);
    names = {};
    status = {};
    profileKey = null;
    planFile = undefined;
    // a restarted klippy counts its errors from 0 again
    lastFault = null;
    lastErrors = null;
    const info = await rpc.call("server.info");
    if (info.klippy_state !== "ready") {
      setConnection("waiting", "klippy " + info.klippy_state);
      sayAll(`klippy is ${info.klippy_state}: the page fills in when it is ready.`);
      return;
    }
    const objects = (await rpc.call("printer.objects.list")).objects;
    const extruders = objects.filter((o) => /^extruder\d*$/.test(o)).sort();
    if (!chosen) {
      const th = await rpc.call("printer.objects.query", {objects: {toolhead: ["extruder"]}});
      extruder = th.status.toolhead.extruder || "extruder";
    }
    extruderLinks(extruders);
    if (!extruders.includes(extruder)) {
      setConnection("live", "connected");
      sayAll(`This printer has no [${extruder}]: its extruders are ` +
             (extruders.join(", ") || "none") + ".");
      return;
    }
    const cfg = await rpc.call("printer.objects.query",
                               {objects: {configfile: ["settings"]}});
    const settings = cfg.status.configfile.settings;
    names = choose(objects, settings, extruder);
    tools = {};
    for (const tool of extruders) tools[tool] = choose(objects, settings, tool);
    const wanted = {print_stats: ["filename", "state"],
                    virtual_sdcard: ["file_position", "file_path"],
                    toolhead: ["extruder"]};
    for (const [tool, own] of Object.entries(tools)) {
      wanted[tool] = ["temperature", "target"];
      for (const obj of [own.sensor, own.limiter, own.autotemp]) {
        if (obj) wanted[obj] = null;
      }
    }
    if (objects.includes("flowloop")) wanted.flowloop = ["profiles"];
    const sub = await rpc.call("printer.objects.subscribe", {objects: wanted});
    merge(sub.status);
    names.ready = true;
    setConnection("live", "live");
    sayAll(null);
    if (!$("#events").children.length) {
      $("#now .message").hidden = false;
      $("#now .message").textContent = "None since the page opened.";
    }
    if (!names.sensor) {
      say("flow-chart", `No [flow_sensor] watches ${extruder}: measured flow and grip ` +
          "need one (see flow_sensor.md; to try it without one, [flow_sensor_simulation NAME]).");
      $("#now .message").hidden = false;
      $("#now .message").textContent = `No [flow_sensor] on ${extruder}: no faults to show.`;
    }
    readout();
    toolsTable();
    sample();
    timelineCharts();
    await refreshLines();
    await refreshPlan(true);
  }

  function onNotify(method, params) {
    if (method === "notify_status_update") {
      onStatus(params[0]);
    } else if ((method === "notify_history_changed" && params[0]
                && params[0].action === "finished")
               || method === "notify_flowloop_nozzle_health") {
      // the report and the verdict are stored as the job ends: ask a moment later
      setTimeout(() => refreshReports().catch(fail), REPORT_DELAY_MS);
    } else if (method === "notify_klippy_ready") {
      start().catch(fail);
    } else if (method === "notify_klippy_disconnected" || method === "notify_klippy_shutdown") {
      names = {};
      setConnection("waiting", method === "notify_klippy_shutdown" ? "klippy shut down"
        : "klippy disconnected");
      notice("klippy " + (method === "notify_klippy_shutdown" ? "shut down" : "disconnected") +
             ": the page goes on when it is back.");
    }
  }

  function fail(err) {
    if (err && err.message === "closed") return;  // the reconnect says it
    // eslint-disable-next-line no-console
    console.warn("flowloop page:", err);
    notice(String(err && err.message ? err.message : err));
  }

  async function connect() {
    setConnection("connecting", "connecting");
    let token;
    try {
      token = await oneshotToken();
    } catch (err) {
      if (err.refused) {
        setConnection("refused", "not authorized");
        sayAll(err.message);
        notice(err.message);
        return;  // nothing to retry with: the user must open it authorised
      }
      setConnection("down", "Moonraker unreachable");
      notice("Moonraker does not answer: trying again.");
      setTimeout(connect, RECONNECT_MS);
      return;
    }
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const url = `${proto}//${location.host}${base}websocket` +
      (token ? "?token=" + encodeURIComponent(token) : "");
    rpc = new Rpc(url, onNotify, () => {
      names = {};
      setConnection("down", "reconnecting");
      notice("The connection to Moonraker is lost: reconnecting.");
      setTimeout(connect, RECONNECT_MS);
    });
    try {
      await rpc.opened;
      notice(null);
      await rpc.call("server.connection.identify", {
        client_name: "flowloop-page", version: "1", type: "web",
        url: location.origin + location.pathname});
      await start();
    } catch (err) {
      fail(err);
    }
  }

  window.addEventListener("resize", () => {
    for (const [id, chart] of Object.entries(charts)) {
      chart.setSize({width: width(document.getElementById(id)), height: CHART_HEIGHT});
    }
  });

  setInterval(sample, SAMPLE_MS);
  connect();
}());

// edgemodbus web console: plain JavaScript, no build step (docs/console.md).
// Every text from the gateway goes through textContent (never innerHTML).
"use strict";

const state = { csrf: null, user: null, required: false, timer: null, source: null };
const PAGE = 100; // tag rows per page

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (value !== null && value !== undefined && value !== false) node.setAttribute(key, value);
  }
  for (const child of children) if (child !== null && child !== undefined) node.append(child);
  return node;
}

async function api(method, path, body) {
  const headers = {};
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (method !== "GET" && state.csrf) headers["X-CSRF-Token"] = state.csrf;
  const resp = await fetch(path, { method, headers, credentials: "same-origin",
    body: body === undefined ? undefined : JSON.stringify(body) });
  let data = null;
  try { data = await resp.json(); } catch (e) { data = { ok: false, error: resp.statusText }; }
  if (resp.status === 401 && path !== "/api/login") { showLogin(); throw new Error("login"); }
  return data;
}

function main(...nodes) {
  const node = document.getElementById("main");
  node.replaceChildren(...nodes);
  return node;
}

function leave() {
  if (state.timer) { clearInterval(state.timer); state.timer = null; }
  if (state.source) { state.source.close(); state.source = null; }
}

function fmt(value) {
  if (value === null || value === undefined) return "";
  if (typeof value === "object") return JSON.stringify(value);
  return String(value);
}

function ms(seconds) { return (1000 * (seconds || 0)).toFixed(1); }

// -- login ---------------------------------------------------------------------------
function showLogin() {
  leave();
  const user = el("input", { id: "login-user", placeholder: "user", autocomplete: "username" });
  const pass = el("input", { id: "login-password", type: "password", placeholder: "password",
    autocomplete: "current-password" });
  const token = el("input", { id: "login-token", type: "password", placeholder: "or token" });
  const out = el("div", { id: "login-result" });
  const form = el("form", { class: "login", onsubmit: async (ev) => {
    ev.preventDefault();
    const body = token.value ? { token: token.value } : { user: user.value, password: pass.value };
    const data = await api("POST", "/api/login", body);
    if (data.ok) { state.csrf = data.csrf; state.user = data.user; showWho(); route(); }
    else out.replaceChildren(el("div", { class: "result bad", text: data.error }));
  } }, el("h2", { text: "Log in" }), user, pass, token,
    el("button", { class: "primary", type: "submit", id: "login-submit", text: "Log in" }), out);
  main(form);
}

function showWho() {
  document.getElementById("who").textContent = state.user ? `logged in as ${state.user}` : "";
  document.getElementById("logout").hidden = !(state.required && state.user);
}

// -- overview ------------------------------------------------------------------------
const COLUMNS = [["code", "Device"], ["status", "Status"], ["line", "Line"], ["slaveId", "Slave"],
  ["items", "Tags"], ["cycleRate", "Cycles/s"], ["lastCycleTime", "Cycle ms"],
  ["cycles", "Cycles"], ["requests", "Requests"], ["responses", "Responses"],
  ["timeouts", "Timeouts"], ["crcErrors", "CRC"], ["exceptions", "Exceptions"],
  ["writes", "Writes"], ["lastError", "Last error"]];

function overviewCell(row, key) {
  if (key === "code") return el("td", {}, el("a", { href: `#/device/${encodeURIComponent(row.code)}`, text: row.code }));
  if (key === "status") return el("td", { class: `status status-${row.status}`, text: row.status });
  if (key === "cycleRate") return el("td", { class: "num", text: row.cycleRate.toFixed(2) });
  if (key === "lastCycleTime") return el("td", { class: "num", text: ms(row.lastCycleTime) });
  const value = row[key];
  return el("td", { class: typeof value === "number" ? "num" : "", text: fmt(value) });
}

async function showOverview() {
  const devices = el("tbody", { id: "devices" });
  const ports = el("tbody", { id: "ports" });
  const dtus = el("tbody", { id: "dtus" });
  main(el("h2", { text: "Devices and lines" }),
    el("table", {}, el("thead", {}, el("tr", {}, ...COLUMNS.map(([, t]) => el("th", { text: t })))), devices),
    el("h3", { text: "DTU listen ports: refusals by kind" }),
    el("table", {}, el("thead", {}, el("tr", {}, el("th", { text: "Port" }), el("th", { text: "Counters" }))), ports),
    el("h3", { text: "DTUs" }),
    el("table", {}, el("thead", {}, el("tr", {}, ...["Port", "DTU id", "Connected", "Peer", "Connections", "Replaced"].map((t) => el("th", { text: t })))), dtus));
  const refresh = async () => {
    const data = await api("GET", "/api/overview");
    devices.replaceChildren(...data.devices.map((row) =>
      el("tr", { "data-code": row.code }, ...COLUMNS.map(([key]) => overviewCell(row, key)))));
    if (!data.devices.length) devices.append(el("tr", {}, el("td", { colspan: COLUMNS.length, class: "muted", text: "No device files in the config folder." })));
    ports.replaceChildren(...Object.entries(data.listeners).map(([port, counts]) =>
      el("tr", {}, el("td", { text: port }), el("td", { class: "value",
        text: Object.entries(counts).filter(([, n]) => n).map(([k, n]) => `${k} ${n}`).join(", ") || "none" }))));
    dtus.replaceChildren(...Object.entries(data.dtus).flatMap(([port, list]) => list.map((d) =>
      el("tr", {}, el("td", { text: port }), el("td", { text: d.dtuId }),
        el("td", { text: d.connected ? "yes" : "no" }), el("td", { text: fmt(d.peer) }),
        el("td", { class: "num", text: d.connections }), el("td", { class: "num", text: d.replaced })))));
  };
  await refresh();
  state.timer = setInterval(() => refresh().catch(() => {}), 2000);
}

// -- a device's tags -------------------------------------------------------------------
async function showDevice(code) {
  const tags = new Map();
  let page = 0;
  let offset = 0; // server clock - ours, ms
  const status = el("span", { id: "device-status", class: "status" });
  const filter = el("input", { id: "tag-filter", placeholder: "filter by name" });
  const only = el("select", { id: "tag-status" }, ...["", "Ok", "Invalid", "Unknown"].map((s) =>
    el("option", { value: s, text: s || "any status" })));
  const pager = el("span", { id: "pager" });
  const body = el("tbody", { id: "tags" });
  const result = el("div", { id: "write-result" });
  const actions = el("div", { id: "actions" });
  const setStatus = (s) => { status.textContent = s; status.className = `status status-${s}`; };

  function shown() {
    const text = filter.value.toLowerCase();
    const want = only.value;
    return [...tags.values()].filter((t) => (!text || t.name.toLowerCase().includes(text)) &&
      (!want || t.status === want));
  }
  function age(t) {
    if (!t.updateTs) return "";
    return ((Date.now() + offset - Date.parse(t.updateTs)) / 1000).toFixed(1) + " s";
  }
  function row(t) {
    const write = t.writable ? el("button", { class: "write", "data-tag": t.name, text: "Write",
      onclick: () => startWrite(t) }) : null;
    return el("tr", { "data-tag": t.name },
      el("td", { text: t.name }), el("td", { text: t.address }), el("td", { text: t.type }),
      el("td", { class: "value", text: fmt(t.value) + (t.unit ? ` ${t.unit}` : "") }),
      el("td", { class: `status status-${t.status}`, text: t.status }),
      el("td", { text: fmt(t.reason) }), el("td", { class: "num age", text: age(t) }),
      el("td", {}, write));
  }
  function render() {
    const list = shown();
    const pages = Math.max(1, Math.ceil(list.length / PAGE));
    page = Math.min(page, pages - 1);
    body.replaceChildren(...list.slice(page * PAGE, (page + 1) * PAGE).map(row));
    pager.replaceChildren(
      el("button", { id: "prev", text: "<", onclick: () => { page = Math.max(0, page - 1); render(); } }),
      ` page ${page + 1} of ${pages} (${list.length} tags) `,
      el("button", { id: "next", text: ">", onclick: () => { page += 1; render(); } }));
  }
  function startWrite(t) {
    const input = el("input", { id: "write-value", value: fmt(t.value) });
    const send = el("button", { class: "primary", id: "write-send", text: `Write ${t.name}`,
      onclick: () => doWrite(t, input.value) });
    result.replaceChildren(el("span", { text: `${t.name} (${t.type}) = ` }), input, send);
    input.focus();
  }
  async function doWrite(t, text) {
    let value = text;
    if (t.type === "Boolean") value = ["1", "true", "on", "yes"].includes(text.trim().toLowerCase());
    else if (!["String", "Binary", "DateTime", "Char"].includes(t.type) && text.trim() !== "" && !isNaN(Number(text))) value = Number(text);
    const data = await api("POST", `/api/devices/${encodeURIComponent(code)}/write`, { name: t.name, value });
    result.replaceChildren(el("div", { id: "write-outcome", class: `result ${data.ok ? "ok" : "bad"}`,
      text: data.ok ? `${t.name} = ${fmt(value)}: confirmed by the slave` : `${t.name}: ${data.error}` }));
  }
  async function load() {
    const data = await api("GET", `/api/devices/${encodeURIComponent(code)}/tags`);
    if (data.ok === false) { leave(); main(el("div", { class: "result bad", text: data.error })); return false; }
    offset = data.serverTime * 1000 - Date.now();
    tags.clear();
    for (const t of data.tags) tags.set(t.name, t);
    setStatus(data.status);
    actions.replaceChildren(...data.actions.map((name) => {
      const params = el("input", { placeholder: "parameters as JSON, e.g. {}", "data-action": name });
      return el("div", { class: "toolbar" }, el("button", { text: `Run ${name}`, onclick: async () => {
        let parsed = {};
        try { parsed = params.value ? JSON.parse(params.value) : {}; } catch (e) {
          result.replaceChildren(el("div", { class: "result bad", text: `parameters: ${e.message}` })); return; }
        const out = await api("POST", `/api/devices/${encodeURIComponent(code)}/action`, { name, params: parsed });
        result.replaceChildren(el("div", { id: "write-outcome", class: `result ${out.ok ? "ok" : "bad"}`,
          text: out.ok ? `action ${name}: confirmed by the slave` : out.error }));
      } }), params);
    }));
    render();
    return true;
  }
  main(el("h2", {}, `Device ${code} `, status),
    el("div", { class: "toolbar" }, filter, only, pager), result, actions,
    el("table", {}, el("thead", {}, el("tr", {}, ...["Name", "Address", "Type", "Value", "Status", "Reason", "Age", ""].map((t) => el("th", { text: t })))), body));
  filter.addEventListener("input", () => { page = 0; render(); });
  only.addEventListener("change", () => { page = 0; render(); });
  // The stream first: on "ready" (subscribed, also after a reconnect) the table is
  // loaded, and the events that come meanwhile are applied after it, in order, so no
  // change falls between the table and the stream.
  const pending = [];
  let loading = null;
  const apply = (event) => {
    if (event.status) setStatus(event.status.status);
    const visible = new Map([...body.children].map((tr) => [tr.dataset.tag, tr]));
    for (const r of event.rows) {
      const t = tags.get(r.name);
      if (!t) continue;
      Object.assign(t, r);
      const tr = visible.get(r.name);
      if (tr) tr.replaceWith(row(t));
    }
  };
  const reload = () => {
    loading = load().then(() => { for (const event of pending.splice(0)) apply(event); })
      .finally(() => { loading = null; });
  };
  const source = new EventSource(`/api/devices/${encodeURIComponent(code)}/events`);
  state.source = source;
  source.addEventListener("ready", reload);
  source.addEventListener("reload", reload);
  const hash = location.hash;
  source.onerror = () => { // refused (no such device yet: a file just saved): try again
    if (source.readyState !== EventSource.CLOSED) return;
    if (!tags.size) main(el("p", { class: "muted", text: `device ${code}: not running (yet), trying again...` }));
    setTimeout(() => { if (state.source === source && location.hash === hash) route(); }, 2000);
  };
  source.onmessage = (ev) => {
    const event = JSON.parse(ev.data);
    if (loading) pending.push(event); else apply(event);
  };
  state.timer = setInterval(() => { for (const td of body.querySelectorAll("td.age")) {
    const t = tags.get(td.parentElement.dataset.tag); if (t) td.textContent = age(t); } }, 1000);
}

// -- commissioning ---------------------------------------------------------------------
const ORG = [{ name: "deviceCode", label: "Device code", type: "string", defaultValue: "" },
  { name: "deviceName", label: "Device name", type: "string", defaultValue: "" }];
const ITEM_FIELDS = ["name", "address", "deviceDataType", "quantity", "dataMultiplier", "unit"];

function fieldInput(p, path) {
  let input;
  if (p.controlType === "switch" || p.type === "bool") {
    input = el("select", {}, el("option", { value: "false", text: "no" }), el("option", { value: "true", text: "yes" }));
    input.value = String(Boolean(p.defaultValue));
  } else if (p.options) {
    input = el("select", {}, ...p.options.map((o) => {
      const v = typeof o === "object" && o !== null ? o.value : o;
      const t = typeof o === "object" && o !== null ? o.label : o;
      return el("option", { value: v === null ? "" : String(v), text: String(t) });
    }));
    input.value = p.defaultValue === null ? "" : String(p.defaultValue);
  } else {
    input = el("input", { type: p.controlType === "password" ? "password" : "text",
      value: p.defaultValue === null || p.defaultValue === undefined ? "" : String(p.defaultValue) });
  }
  input.dataset.path = path;
  input.dataset.type = p.type || "string";
  input.dataset.default = p.defaultValue === null || p.defaultValue === undefined ? "" : String(p.defaultValue);
  input.name = path;
  return input;
}

function typed(input) {
  const text = input.value;
  if (input.dataset.type === "bool") return text === "true";
  if (input.dataset.type === "int" || input.dataset.type === "float") {
    const n = Number(text);
    return text.trim() !== "" && !isNaN(n) ? n : text; // a bad number goes as typed: the check names it
  }
  return text;
}

async function showCommission() {
  const desc = await api("GET", "/api/descriptor");
  const fields = el("div", { class: "form-grid", id: "device-form" });
  const inputs = [];
  const addField = (p, path) => {
    const input = fieldInput(p, path);
    inputs.push([p, input]);
    fields.append(el("div", { class: "field", "data-field": path, "data-visible-when": p.visibleWhen ? JSON.stringify(p.visibleWhen) : null },
      el("label", { text: `${p.label || p.name} (${p.name})` }), input,
      el("span", { class: "hint", text: p.description || "" }), el("span", { class: "field-error" })));
  };
  const fileName = el("input", { id: "file-name", value: "new-device.json" });
  const overwrite = el("input", { type: "checkbox", id: "overwrite" });
  fields.append(el("div", { class: "field", "data-field": "fileName" },
    el("label", { text: "File name (in the config folder)" }), fileName, el("span", { class: "field-error" })));
  for (const p of ORG) addField(p, `organization.${p.name}`);
  for (const p of desc.parameter) addField(p, `communication.${p.name}`);
  const items = el("tbody", { id: "items" });
  const types = desc.supportedDataTypes;
  const addItem = (item) => {
    const i = items.children.length;
    const cells = ITEM_FIELDS.map((key) => {
      const input = key === "deviceDataType" ? el("select", {}, ...types.map((t) => el("option", { value: t, text: t })))
        : el("input", { placeholder: key });
      input.value = item[key] === undefined ? (key === "deviceDataType" ? "UInt16" : "") : String(item[key]);
      input.dataset.path = `addressList[${i}].${key}`;
      return el("td", { "data-field": `addressList[${i}].${key}` }, input, el("span", { class: "field-error" }));
    });
    items.append(el("tr", {}, ...cells));
  };
  addItem({ name: "t0", address: "hr:0" });
  const general = el("div", { id: "form-problems" });
  const plan = el("pre", { class: "plan", id: "plan", hidden: true });
  const visibility = () => {
    const values = Object.fromEntries(inputs.map(([p, input]) => [p.name, typed(input)]));
    for (const node of fields.querySelectorAll("[data-visible-when]")) {
      const when = JSON.parse(node.dataset.visibleWhen);
      node.hidden = !Object.entries(when).every(([k, v]) => values[k] === v);
    }
  };
  for (const [, input] of inputs) input.addEventListener("change", visibility);
  const documentOf = () => {
    const doc = { driverType: desc.driverType, organization: {}, communication: {}, addressList: [] };
    for (const [p, input] of inputs) {
      const [section, key] = input.dataset.path.split(".");
      const hidden = input.closest(".field").hidden;
      if (section === "organization") { if (input.value !== "") doc.organization[key] = typed(input); continue; }
      if (hidden || key === "useTcp") continue;
      if (input.value === input.dataset.default && key !== "transport") continue; // defaults stay implicit
      if (input.value === "" && p.type !== "string") continue;
      doc.communication[key] = typed(input);
    }
    for (const tr of items.children) {
      const item = {};
      for (const input of tr.querySelectorAll("[data-path]")) {
        const key = input.dataset.path.split(".")[1];
        if (input.value === "") continue;
        item[key] = ["quantity", "dataMultiplier"].includes(key) && !isNaN(Number(input.value)) ? Number(input.value) : input.value;
      }
      if (Object.keys(item).length) doc.addressList.push(item);
    }
    return doc;
  };
  const showProblems = (problems) => {
    for (const node of document.querySelectorAll(".has-error")) node.classList.remove("has-error");
    for (const node of document.querySelectorAll(".field-error")) node.textContent = "";
    const rest = [];
    for (const p of problems) {
      const holder = document.querySelector(`[data-field="${CSS.escape(p.path)}"]`);
      // the field is where it shows; the value and the rule are the problem's text after its path
      const said = p.text.startsWith(p.path) ? p.text.slice(p.path.length).trim() : p.text;
      if (holder) { holder.classList.add("has-error"); holder.querySelector(".field-error").textContent = said; }
      else rest.push(p.text);
    }
    general.replaceChildren(...(problems.length ? [el("div", { class: "result bad", text: `${problems.length} problem(s)` })] : []),
      ...rest.map((t) => el("div", { class: "result bad", text: t })));
    const first = document.querySelector(".has-error");
    if (first) first.scrollIntoView({ block: "center" });
  };
  const check = async () => {
    const data = await api("POST", "/api/commission/check", { document: documentOf() });
    showProblems(data.problems || []);
    if (data.ok) {
      plan.hidden = false;
      plan.textContent = `${data.plan.items} tags, ${data.plan.requests.length} requests per cycle ` +
        `(slave ${data.plan.slaveId} on ${data.plan.line})\n` + data.plan.requests.map((r) =>
        `  FC${String(r.function).padStart(2, "0")} ${r.area}:${r.start}-${r.start + r.count - 1} (${r.count}) every ${r.every} ms: ${r.items.join(", ")}`).join("\n");
    } else plan.hidden = true;
    return data.ok;
  };
  const save = async () => {
    const data = await api("POST", "/api/commission/save", { fileName: fileName.value, document: documentOf(), overwrite: overwrite.checked });
    showProblems(data.problems || []);
    if (data.ok) {
      general.replaceChildren(el("div", { class: "result ok", id: "save-result",
        text: `saved ${data.file}; the gateway reloads it` }), " ",
        el("a", { href: `#/device/${encodeURIComponent(data.code)}`, id: "saved-device", text: `open ${data.code}` }));
    } else if (data.error) general.replaceChildren(el("div", { class: "result bad", text: data.error }));
  };
  main(el("h2", { text: "Add a device (from the driver descriptor)" }), fields,
    el("h3", { text: "Tags" }),
    el("table", {}, el("thead", {}, el("tr", {}, ...ITEM_FIELDS.map((k) => el("th", { text: k })))), items),
    el("div", { class: "toolbar" },
      el("button", { id: "add-item", text: "Add a tag", onclick: () => addItem({ name: `t${items.children.length}`, address: `hr:${items.children.length}` }) }),
      el("button", { id: "check", text: "Check and preview the read plan", onclick: check }),
      el("label", {}, overwrite, " replace an existing file"),
      el("button", { class: "primary", id: "save", text: "Save and reload", onclick: save })),
    general, plan);
  visibility();
}

// -- routing -----------------------------------------------------------------------------
async function route() {
  leave();
  if (state.required && !state.user) { showLogin(); return; }
  const hash = location.hash || "#/";
  try {
    if (hash.startsWith("#/device/")) await showDevice(decodeURIComponent(hash.slice(9)));
    else if (hash === "#/commission") await showCommission();
    else await showOverview();
  } catch (e) {
    if (e.message !== "login") main(el("div", { class: "result bad", text: String(e) }));
  }
}

async function boot() {
  const session = await (await fetch("/api/session", { credentials: "same-origin" })).json();
  Object.assign(state, { csrf: session.csrf, user: session.user, required: session.required });
  document.getElementById("gateway-id").textContent = `gateway ${session.gatewayId}`;
  document.getElementById("logout").addEventListener("click", async () => {
    await api("POST", "/api/logout", {}); state.user = null; state.csrf = null; showWho(); showLogin();
  });
  showWho();
  window.addEventListener("hashchange", route);
  await route();
}

boot();

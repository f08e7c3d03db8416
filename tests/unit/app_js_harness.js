// Runs the dashboard's page script (ccrp_cli/dashboard/static/app.js) in Node on a stand-in DOM,
// with fake timers and a recording fetch, through the scenario named in argv[3]; prints what the
// page sent at each step as JSON (tests/unit/test_dashboard_page.py reads it). No browser.
"use strict";
const fs = require("fs");
const vm = require("vm");

const [, , appPath, scenario] = process.argv;

// Timers: run only when the scenario advances the clock.
let now = 0, nextId = 1;
const timers = new Map();
function addTimer(fn, ms, repeat) {
  const id = nextId++;
  timers.set(id, {fn, at: now + Math.max(0, ms || 0), every: repeat ? Math.max(1, ms || 0) : null});
  return id;
}
async function settle() { for (let i = 0; i < 20; i++) await new Promise((r) => setImmediate(r)); }
async function advance(ms) {
  const end = now + ms;
  for (;;) {
    const due = [...timers.entries()].filter(([, t]) => t.at <= end).sort((a, b) => a[1].at - b[1].at)[0];
    if (!due) break;
    const [id, t] = due;
    now = t.at;
    if (t.every) t.at += t.every; else timers.delete(id);
    t.fn();
    await settle();
  }
  now = end;
  await settle();
}

// The DOM, as far as the page uses it.
function listeners() {
  const map = {};
  return {
    addEventListener(type, fn) { (map[type] = map[type] || []).push(fn); },
    dispatch(type, ev) { for (const fn of map[type] || []) fn(ev); },
  };
}
const elements = {};
function element(tag, id) {
  const e = {
    ...listeners(), tagName: (tag || "div").toUpperCase(), id, value: "", textContent: "", className: "", hidden: false,
    dataset: {}, options: [], children: [], disabled: false, title: "", src: "",
    classList: {add() {}, remove() {}, contains() { return false; }},
    blur() {}, focus() {}, scrollIntoView() {}, removeAttribute() {}, remove() {},
    append(...c) { this.children.push(...c); }, prepend(...c) { this.children.unshift(...c); },
    replaceChildren(...c) { this.children = c; }, querySelector() { return null; }, querySelectorAll() { return []; },
  };
  return e;
}
const document = {
  ...listeners(), hidden: false, activeElement: null,
  querySelector(sel) { return sel === 'meta[name="ccrp-csrf"]' ? {content: "csrf-of-this-page"} : null; },
  querySelectorAll() { return []; },
  getElementById(id) { return elements[id] || (elements[id] = element("div", id)); },
  createElement(tag) { return element(tag); },
};
const windowObj = listeners();

// fetch: recorded; answers as the scenario says (a function of the request).
const sent = [];
let answer = () => ({status: 200, body: {ok: true}});
async function fetchFake(url, opts = {}) {
  const req = {url, method: opts.method || "GET", csrf: (opts.headers || {})["X-CCRP-CSRF"] || null,
               body: opts.body ? JSON.parse(opts.body) : null};
  sent.push(req);
  const {status, body, blob} = answer(req);
  return {
    ok: status >= 200 && status < 300, status,
    json: async () => body, text: async () => JSON.stringify(body), blob: async () => blob || "jpeg-bytes",
    headers: {get: (name) => ({"X-CCRP-Frame-Seq": "7", "X-CCRP-Frame-Size": "16x8"})[name] || null},
  };
}
class FileReader { readAsDataURL() { setImmediate(() => { this.result = "data:image/jpeg;base64,AA=="; this.onload(); }); } }
class EventSource { constructor() { this.readyState = 1; } addEventListener() {} }
EventSource.CLOSED = 2;

const context = vm.createContext({
  document, window: windowObj, fetch: fetchFake, FileReader, EventSource, console,
  setTimeout: (fn, ms) => addTimer(fn, ms, false), clearTimeout: (id) => timers.delete(id),
  setInterval: (fn, ms) => addTimer(fn, ms, true), clearInterval: (id) => timers.delete(id),
  alert: () => {}, confirm: () => true, location: {replace() {}}, Date: {now: () => now},
  encodeURIComponent, JSON, Promise, Number, Object, Math, String, parseFloat, parseInt, Array, Map, Set,
});
vm.runInContext(fs.readFileSync(appPath, "utf8"), context, {filename: "app.js"});

const teleops = () => sent.filter((r) => r.url === "/api/teleop").map((r) => [r.body.linear, r.body.angular]);
const key = (type, k) => document.dispatch(type, {key: k, target: {tagName: "BODY"}, preventDefault() {},
                                                   ctrlKey: false, metaKey: false, altKey: false});

async function main() {
  document.dispatch("DOMContentLoaded", {});
  const steps = {};
  const mark = (name) => { steps[name] = teleops(); sent.length = 0; };
  if (scenario === "drive") {
    Object.assign(document.getElementById("teleop-robot"), {value: "nao1"});
    Object.assign(document.getElementById("teleop-linear"), {value: "0.2"});
    Object.assign(document.getElementById("teleop-angular"), {value: "0.5"});
    key("keydown", "ArrowUp");
    await settle();
    mark("pressed");
    await advance(1000);  // held, no keyboard repeat: the page says it again
    mark("held 1 s");
    windowObj.dispatch("blur", {});  // another window took the keyboard: no keyup will come
    await settle();
    mark("blur");
    await advance(2000);
    mark("after blur");
    key("keydown", "d");
    await settle();
    await advance(400);
    document.hidden = true;
    document.dispatch("visibilitychange", {});
    await settle();
    mark("hidden");
    await advance(2000);
    mark("after hidden");
    windowObj.dispatch("blur", {});  // nothing moves: no command
    await settle();
    mark("blur at rest");
    document.hidden = false;
    key("keydown", "w");
    await settle();
    key("keyup", "w");
    await settle();
    await advance(1000);
    mark("pressed and let go");
  } else if (scenario === "camera") {
    let agent = false;
    answer = (req) => {
      if (req.url.endsWith("/start")) { agent = true; return {status: 200, body: {robot: "nao1", agent: "started"}}; }
      if (req.url.startsWith("/api/camera/")) {
        return agent ? {status: 200, body: null} : {status: 503, body: {error: "no camera agent runs", why: "no-agent"}};
      }
      return {status: 200, body: {ok: true}};
    };
    const cams = () => sent.filter((r) => r.url.startsWith("/api/camera/")).map((r) => [r.method, r.url, r.csrf]);
    const select = document.getElementById("camera-robot");
    select.value = "nao1";
    select.dispatch("change", {target: select});
    await settle();
    steps["chosen"] = cams(); sent.length = 0;
    await advance(2100);
    steps["next poll"] = cams(); sent.length = 0;
    agent = false;  // it ended (idle): the next read says so, and the page starts it again, once
    await advance(2100);
    await advance(2100);
    steps["agent ended"] = cams(); sent.length = 0;
    answer = (req) => req.url.endsWith("/start") ? {status: 503, body: {error: "no clone", why: "no-clone"}}
                                                 : {status: 503, body: {error: "no camera agent runs", why: "no-agent"}};
    agent = false;
    await advance(2100);
    await advance(2100);
    await advance(2100);
    steps["start refused"] = cams(); sent.length = 0;
    steps["info"] = document.getElementById("camera-info").textContent;
  }
  process.stdout.write(JSON.stringify(steps));
}
main().catch((e) => { console.error(e && e.stack || e); process.exit(1); });

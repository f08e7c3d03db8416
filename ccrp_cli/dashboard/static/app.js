// ccrp dashboard: renders the `fleet` and `action` server-sent events; starts actions with POST.
// No framework, no third-party script (the Content-Security-Policy allows this file only).
"use strict";

const CSRF = document.querySelector('meta[name="ccrp-csrf"]').content;

// Per-robot controls, each a function (row) -> array of elements for the row's Actions cell.
const ROBOT_ACTIONS = [
  (row) => !row.power ? [] : row.power.relay === "off"
    ? [button("Power on", `switch ${row.robot} on through its power device (= ccrp robot power on --robot ${row.robot})`,
              () => act("robot-power", {robot: row.robot, state: "on"}))]
    : [button("Power off", `cut ${row.robot}'s power through its power device (= ccrp robot power off --robot ${row.robot})`,
              () => confirm(`Switch robot ${row.robot} off? Its computer stops at once (VPN, ROS nodes, watchdog).`)
                    && act("robot-power", {robot: row.robot, state: "off"}), "danger power")],
  (row) => row.vpn_connected && !row.revoked_at
    ? [button("Drive", `teleoperate ${row.robot} from this page (keys or the pad below)`,
              () => chooseDriven(row.robot), "drive")]
    : [],
  (row) => row.vpn_connected && !row.revoked_at
    ? [button("Camera", `show ${row.robot}'s camera as its clone sees it, every 2 s (= ccrp robot camera --robot ${row.robot})`,
              () => chooseCamera(row.robot), "camera")]
    : [],
  (row) => row.state === "stopped"
    ? [button("Start", `start the clone of ${row.robot} (= ccrp clone start --robot ${row.robot})`,
              () => act("clone-start", {robot: row.robot}))]
    : row.state === "running"
    ? [button("Restart", `stop the clone of ${row.robot} and start it again (= ccrp clone restart --robot ${row.robot})`,
              () => confirm(`Restart the clone of ${row.robot}? Its robot is brainless until it serves again.`)
                    && act("clone-restart", {robot: row.robot}))]
    : [],
  (row) => row.revoked_at ? [] : [
    button("Revoke", `revoke ${row.robot}: its session ends, it stays out until vpn issue-cert`,
           () => confirm(`Revoke robot ${row.robot}? Its VPN session ends now and it stays out ` +
                         `until \`ccrp vpn issue-cert --robot ${row.robot}\`.`)
                 && act("vpn-revoke", {robot: row.robot}), "danger")],
];

let busy = false;  // an action queued or running: the server runs them one at a time

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function button(label, title, onclick, cls) {
  const b = el("button", label, cls);
  b.title = title;
  b.disabled = busy && cls !== "drive" && cls !== "camera";  // driving and looking never wait behind an action
  b.addEventListener("click", onclick);
  return b;
}

async function act(kind, args) {
  const r = await fetch(`/api/actions/${kind}`, {
    method: "POST", credentials: "same-origin",
    headers: {"Content-Type": "application/json", "X-CCRP-CSRF": CSRF},
    body: JSON.stringify(args),
  });
  if (!r.ok) {
    let why = `${r.status}`;
    try { why += ": " + (await r.json()).error; } catch (e) { why += ": " + await r.text(); }
    alert(`The dashboard refused the action (${why})`);
  }
}

async function logout() {
  const r = await fetch("/api/logout", {method: "POST", credentials: "same-origin", headers: {"X-CCRP-CSRF": CSRF}});
  // 401: the session had already ended. Either way "/" is now the page asking for the token.
  if (r.ok || r.status === 401) location.replace("/");
  else alert(`The dashboard refused to log out (${r.status}: ${await r.text()})`);
}

function vpnCell(row) {
  if (row.vpn_connected) {
    const rtt = row.robot_rtt_ms === null || row.robot_rtt_ms === undefined ? "" : `, rtt ${row.robot_rtt_ms.toFixed(1)} ms`;
    return ["connected " + (row.robot_address || "") + rtt, row.revoked_at ? "bad" : "ok"];
  }
  if (row.revoked_at) return ["revoked " + row.revoked_at.slice(0, 10), "bad"];
  if (row.secrets === false) return ["no (keys gone: fleet up)", "bad"];
  return ["no", row.state === "running" ? "warn" : "off"];
}

function nodesCell(row) {
  if (row.stale_nodes && row.stale_nodes.length) return ["stale: " + row.stale_nodes.join(", "), "warn"];
  return [(row.robot_nodes || []).join(", ") || "-", row.robot_nodes && row.robot_nodes.length ? "ok" : "off"];
}

function relayCell(row) {
  const peers = Object.entries(row.relay_peers || {});
  if (!peers.length) return ["-", "off"];
  const down = peers.filter(([, up]) => !up).map(([p]) => p).sort();
  if (!row.relay_running) return [`0/${peers.length} (relay not running)`, "bad"];
  return [`${peers.length - down.length}/${peers.length}` + (down.length ? ` (down: ${down.join(", ")})` : ""),
          down.length ? "warn" : "ok"];
}

function watchdogCell(row) {
  // The robot's own watchdog (a simulated robot here) or, for a real robot, what its clone sees.
  const w = row.watchdog;
  if (!w || w.state === "unknown") return ["-", "off"];
  let text = w.state + (w.since ? ` since ${new Date(w.since).toLocaleTimeString()}` : "");
  if (w.state === "off") return ["off (robot powered off)", "off"];
  if (w.state === "brainless" && w.motors) text += ` (motors ${w.motors})`;
  if (w.source === "clone") text += " (seen from clone)";
  return [text, w.state === "connected" ? "ok" : w.state === "brainless" ? "bad" : "warn"];
}

function powerCell(row) {
  // A power device ccrp reaches (a simulated robot's stand-in, reporting every 3 s), or none.
  const p = row.power;
  if (!p) return ["-", "off"];
  if (!p.relay) return ["on (device not started)", "ok"];
  let text = p.relay + (p.robot === "starting" ? " (robot starting)" : "");
  if (p.silent) text += ` (device silent ${Math.round(p.age_s)} s)`;
  return [text, p.silent ? "warn" : p.relay === "on" ? "ok" : "off"];
}

function ownNodesCell(row) {
  // The robot's own software on its clone (docs/workloads.md): each node's unit state and restarts.
  const nodes = row.nodes || [];
  if (!nodes.length) return ["-", "off"];
  const text = nodes.map((n) => n.name + " " + n.state + (n.restarts ? ` (${n.restarts} restarts)` : "")).join(", ");
  const bad = nodes.some((n) => n.state === "failed" || n.sub === "auto-restart" || (n.restarts || 0) >= 3);
  return [text, bad ? "bad" : nodes.every((n) => n.state === "active") ? "ok" : "warn"];
}

function stateCell(row) {
  // row.state is ccrp's word for it on every provider; row.status the provider's (ACTIVE, exited...)
  const cls = row.state === "running" ? "ok" : row.state === "stopped" ? "warn" : "bad";
  return [row.status + (row.phase && row.phase !== "ready" ? ` (${row.phase})` : ""), cls];
}

function renderFleet(data) {
  document.getElementById("provider").textContent = data.provider;
  // ROS 2 has no master: the column says whether the clone's graph answers (as `ccrp status` does).
  document.getElementById("col-master").textContent = data.ros2 ? "Graph" : "Master";
  document.getElementById("updated").textContent =
    `status read ${new Date(data.read_at).toLocaleTimeString()} in ${data.read_seconds} s (every ${data.interval} s)`;
  const body = document.getElementById("robots");
  const rows = data.rows || [];
  body.replaceChildren(...rows.map((row) => {
    const tr = el("tr");
    tr.dataset.robot = row.robot;
    const cells = [
      [row.robot, ""], [row.clone + (row.vpn_endpoint || row.public_ip ? ` (${row.vpn_endpoint || row.public_ip})` : ""), ""], stateCell(row),
      vpnCell(row), [row.status === "running" ? (row.master_reachable ? "yes" : "no") : "-",
                     row.status !== "running" ? "off" : row.master_reachable ? "ok" : "bad"],
      nodesCell(row), ownNodesCell(row), relayCell(row), watchdogCell(row), powerCell(row),
    ];
    const names = ["robot", "clone", "state", "vpn", "master", "nodes", "own", "relay", "watchdog", "power"];
    cells.forEach(([text, cls], i) => { const td = el("td", text, cls); td.dataset.col = names[i]; tr.append(td); });
    const actions = el("td", null, "actions");
    actions.dataset.col = "actions";
    for (const make of ROBOT_ACTIONS) actions.append(...make(row));
    tr.append(actions);
    return tr;
  }));
  if (!rows.length) {
    const tr = el("tr");
    tr.append(el("td", data.rows ? "no robots" : "status unavailable", "off"));
    body.append(tr);
  }
  renderDriveChoices(rows);
  renderCameraChoices(rows);
  const size = document.getElementById("scale-size");
  if (document.activeElement !== size && !size.dataset.touched) size.value = rows.length;
  renderAlerts(data.alerts || []);
}

function renderAlerts(alerts) {
  const list = document.getElementById("alerts");
  const order = {error: 0, warning: 1, info: 2};
  const sorted = [...alerts].sort((a, b) => order[a.level] - order[b.level]);
  list.replaceChildren(...sorted.map((a) => {
    const li = el("li", null, a.level);
    li.dataset.kind = a.kind;
    if (a.robot) li.dataset.robot = a.robot;
    li.append(el("span", a.level, "level"), el("span", a.text, "text"));
    return li;
  }));
  if (!alerts.length) list.append(el("li", "no alerts", "none"));
  const serious = alerts.filter((a) => a.level !== "info").length;
  document.getElementById("alert-count").textContent = serious ? String(serious) : "";
}

const actionItems = new Map();

function renderAction(a) {
  const list = document.getElementById("actions");
  list.querySelector(".none")?.remove();
  let li = actionItems.get(a.id);
  if (!li) {
    li = el("li");
    actionItems.set(a.id, li);
    list.prepend(li);
  }
  li.className = a.state;
  li.dataset.id = a.id;
  const head = el("div", null, "head");
  head.append(el("span", a.state, "state"), el("code", "ccrp " + a.title), el("span", a.ended_at || a.started_at || "", "when"));
  const body = [head];
  if (a.lines.length) body.push(el("pre", a.lines.join("\n")));
  if (a.error) body.push(el("div", a.error, "error"));
  if (Array.isArray(a.result) && a.result.length) {
    body.push(el("div", a.result.map((r) => r.robot ? `${r.robot}: ${r.action}` : r.cn ? `${r.cn} revoked` : JSON.stringify(r)).join(", "), "result"));
  }
  li.replaceChildren(...body);
  busy = [...actionItems.values()].some((item) => item.className === "queued" || item.className === "running");
  document.querySelectorAll("td.actions button:not(.drive):not(.camera), #scale-button").forEach((b) => { b.disabled = busy; });
}

// Teleoperation: one command in flight per page; a key pressed meanwhile replaces the command
// waiting to go, so the robot gets the key's latest state and commands never pile up.
// A held key is sent again every DRIVE_REPEAT_MS: the robot stops by itself when no command came
// for 0.5 s (its deadman, templates/edge/ccrp-demo-node), so a held key must keep saying so. The
// page losing focus or being hidden stops the robot and forgets the held key: its keyup would go
// to another window, and the robot would drive on.
const DRIVE = {forward: [1, 0], back: [-1, 0], left: [0, 1], right: [0, -1], stop: [0, 0]};
const KEYS = {ArrowUp: "forward", w: "forward", ArrowDown: "back", s: "back", ArrowLeft: "left", a: "left",
              ArrowRight: "right", d: "right", " ": "stop", x: "stop"};
const DRIVE_REPEAT_MS = 200;
let driving = false, nextDrive = null;
let heldKey = null, heldTimer = null;  // the drive key held down, and its repeat
let moving = false;  // this page's last command (sent or waiting) was not a stop

// The connected robots as the options of a <select> (its first option stays); false when the
// robot chosen there is gone.
function renderRobotChoices(id, rows) {
  const select = document.getElementById(id);
  const want = rows.filter((r) => r.vpn_connected && !r.revoked_at).map((r) => r.robot);
  const have = [...select.options].slice(1).map((o) => o.value);
  if (want.join() === have.join()) return true;
  const chosen = select.value;
  select.replaceChildren(select.options[0], ...want.map((r) => { const o = el("option", r); o.value = r; return o; }));
  select.value = want.includes(chosen) ? chosen : "";
  return select.value === chosen;
}

function renderDriveChoices(rows) {
  renderRobotChoices("teleop-robot", rows);
}

function chooseDriven(robot) {
  const select = document.getElementById("teleop-robot");
  if (![...select.options].some((o) => o.value === robot)) {
    const o = el("option", robot); o.value = robot; select.append(o);
  }
  select.value = robot;
  select.blur();  // the arrow keys drive the robot, not the list
  document.getElementById("teleop-section").scrollIntoView({block: "nearest"});
}

function drive(name) {
  const robot = document.getElementById("teleop-robot").value;
  if (!robot) { showDrive({ok: false, error: "choose a connected robot first"}); return; }
  const [l, a] = DRIVE[name];
  const speed = parseFloat(document.getElementById("teleop-linear").value) || 0;
  const turn = parseFloat(document.getElementById("teleop-angular").value) || 0;
  nextDrive = {robot, linear: l * speed, angular: a * turn};
  moving = nextDrive.linear !== 0 || nextDrive.angular !== 0;
  if (!driving) sendDrive();
}

function holdKey(name) {
  // A drive key pressed (or repeated by the keyboard): driven now and every DRIVE_REPEAT_MS while held.
  heldKey = name === "stop" ? null : name;
  clearInterval(heldTimer);
  heldTimer = heldKey ? setInterval(() => { if (heldKey) drive(heldKey); }, DRIVE_REPEAT_MS) : null;
  drive(name);
}

function releaseKeys() {
  // Every key let go, the robot stopped: a key released, the page left (blur) or hidden.
  const was = heldKey !== null || moving;
  heldKey = null;
  clearInterval(heldTimer);
  heldTimer = null;
  if (was && document.getElementById("teleop-robot").value) drive("stop");
}

async function sendDrive() {
  const cmd = nextDrive;
  nextDrive = null;
  if (!cmd) return;
  driving = true;
  document.getElementById("teleop").classList.add("sending");
  try {
    const r = await fetch("/api/teleop", {
      method: "POST", credentials: "same-origin",
      headers: {"Content-Type": "application/json", "X-CCRP-CSRF": CSRF},
      body: JSON.stringify(cmd),
    });
    let got;
    try { got = await r.json(); } catch (e) { got = {ok: false, error: `${r.status}`}; }
    if (r.status !== 409) showDrive({...cmd, ...got, ok: r.ok && got.ok !== false});
  } catch (e) {
    showDrive({...cmd, ok: false, error: String(e)});
  } finally {
    driving = false;
    document.getElementById("teleop").classList.remove("sending");
    if (nextDrive) sendDrive();
  }
}

function showDrive(r) {
  const last = document.getElementById("teleop-last");
  const ms = (v) => (v === null || v === undefined) ? "-" : `${Number(v).toFixed(1)} ms`;
  last.className = r.ok ? "ok" : "bad";
  last.dataset.robot = r.robot || "";
  last.dataset.linear = r.linear ?? "";
  last.dataset.angular = r.angular ?? "";
  last.dataset.oneWayMs = r.one_way_ms ?? "";
  last.dataset.roundTripMs = r.round_trip_ms ?? "";
  last.dataset.requestMs = r.request_ms ?? "";
  last.dataset.via = r.via || "";
  if (!r.ok) { last.textContent = `${r.robot ? r.robot + ": " : ""}not sent: ${r.error || "failed"}`; return; }
  const what = `${r.robot}: linear ${r.linear} m/s, angular ${r.angular} rad/s`;
  last.textContent = r.acknowledged
    ? `${what}: reached the robot in ${ms(r.one_way_ms)} (clone → robot), round trip ${ms(r.round_trip_ms)}; ` +
      `request ${ms(r.request_ms)} (page → clone → robot → page` +
      (r.via === "operator" ? ", through the operator node kept on the clone)" : ", starting a node on the clone)")
    : `${what}: published on the clone; the robot sends no acknowledgement, latency unknown`;
}

// Camera: choosing a robot starts its camera agent on the clone (POST /api/camera/ROBOT/start, with
// the CSRF token: a GET never starts anything), then one frame at a time from the clone (GET
// /api/camera/ROBOT), the next asked for 2 s after the last answer, only while the page is shown
// and a connected robot is chosen. An agent that ended since (idle while the page was hidden, the
// clone restarted) is started again once; a start that failed is not retried until chosen again.
const CAMERA_EVERY_MS = 2000;
let cameraTimer = null, cameraReading = false, cameraShown = null;  // cameraShown: the frame on screen, to age it
let cameraNeedsStart = false, cameraHadFrame = false;

function renderCameraChoices(rows) {
  if (!renderRobotChoices("camera-robot", rows)) cameraChanged();  // its robot left: the view stops
}

function chooseCamera(robot) {
  const select = document.getElementById("camera-robot");
  if (![...select.options].some((o) => o.value === robot)) {
    const o = el("option", robot); o.value = robot; select.append(o);
  }
  select.value = robot;
  cameraChanged();
  document.getElementById("camera-section").scrollIntoView({block: "nearest"});
}

function cameraChanged() {
  const robot = document.getElementById("camera-robot").value;
  document.getElementById("camera-view").hidden = !robot;
  cameraShown = null;
  const img = document.getElementById("camera-img");
  img.removeAttribute("src");
  img.dataset.robot = "";
  const info = document.getElementById("camera-info");
  info.textContent = robot ? "waiting for a frame…" : "";
  info.className = "off";
  clearTimeout(cameraTimer);
  cameraTimer = null;
  cameraNeedsStart = !!robot;
  cameraHadFrame = false;
  if (robot) readCamera();
}

async function startCamera(robot) {
  // null: started (or already running); otherwise why not.
  const r = await fetch(`/api/camera/${encodeURIComponent(robot)}/start`, {
    method: "POST", credentials: "same-origin", cache: "no-store", headers: {"X-CCRP-CSRF": CSRF},
  });
  if (r.ok) return null;
  let why = `${r.status}`;
  try { why = (await r.json()).error || why; } catch (e) { /* not JSON */ }
  return why;
}

function dataUrl(blob) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();  // a data: URL: the page's policy allows no blob: images
    reader.onload = () => resolve(reader.result);
    reader.onerror = () => reject(reader.error);
    reader.readAsDataURL(blob);
  });
}

async function readCamera() {
  cameraTimer = null;
  const robot = document.getElementById("camera-robot").value;
  if (!robot) return;
  if (document.hidden || cameraReading) return;  // visibilitychange starts it again; one read at a time
  cameraReading = true;
  const info = document.getElementById("camera-info");
  const img = document.getElementById("camera-img");
  try {
    if (cameraNeedsStart) {
      cameraNeedsStart = false;
      if (!cameraShown) { info.textContent = "starting the camera agent on the clone…"; info.className = "off"; }
      const failed = await startCamera(robot);
      if (document.getElementById("camera-robot").value !== robot) return;  // another robot chosen meanwhile
      if (failed) {
        img.classList.add("stale");
        info.textContent = `camera not started: ${failed}`;
        info.className = "bad";
        return;
      }
    }
    const r = await fetch(`/api/camera/${encodeURIComponent(robot)}`, {credentials: "same-origin", cache: "no-store"});
    if (document.getElementById("camera-robot").value !== robot) return;  // another robot chosen meanwhile
    if (!r.ok) {
      let why = `${r.status}`, body = {};
      try { body = await r.json(); why = body.error || why; } catch (e) { /* not JSON */ }
      if (body.why === "no-agent" && cameraHadFrame) {  // it ended since the last frame: started again next
        cameraHadFrame = false;
        cameraNeedsStart = true;
      }
      img.classList.add("stale");
      info.textContent = `no frame: ${why}`;
      info.className = "bad";
      return;
    }
    cameraHadFrame = true;
    const h = (name) => r.headers.get(`X-CCRP-Frame-${name}`);
    const src = await dataUrl(await r.blob());
    if (document.getElementById("camera-robot").value !== robot) return;
    img.src = src;
    img.classList.remove("stale");
    Object.assign(img.dataset, {robot, seq: h("Seq") || "", size: h("Size") || "", encoding: h("Encoding") || "",
                                ageMs: h("Age-Ms") || "", readMs: h("Read-Ms") || "", stamp: h("Stamp") || ""});
    const stamp = parseFloat(h("Stamp"));
    cameraShown = {robot, topic: h("Topic"), size: h("Size"), encoding: h("Encoding"), seq: h("Seq"),
                   ageMs: parseFloat(h("Age-Ms")), readMs: parseFloat(h("Read-Ms")),
                   stamp: Number.isFinite(stamp) ? stamp : null, at: Date.now()};
    showCameraAge();
  } catch (e) {
    info.textContent = `no frame: ${e}`;
    info.className = "bad";
  } finally {
    cameraReading = false;
    const now = document.getElementById("camera-robot").value;
    clearTimeout(cameraTimer);
    // The same robot: again in 2 s; another one chosen while this read ran: at once.
    cameraTimer = now ? setTimeout(readCamera, now === robot ? CAMERA_EVERY_MS : 0) : null;
  }
}

function showCameraAge() {
  const f = cameraShown;
  if (!f) return;
  const info = document.getElementById("camera-info");
  // The frame's age now: its age when the clone read it, plus the time since this page got it.
  const sinceRead = (Date.now() - f.at) / 1000 + (f.readMs || 0) / 1000;
  const age = Number.isFinite(f.ageMs) ? f.ageMs / 1000 + sinceRead : null;
  info.className = "ok";
  info.dataset.ageS = age === null ? "" : age.toFixed(1);
  info.textContent = `${f.robot} ${f.topic} ${f.size} ${f.encoding}, frame #${f.seq}` +
    (f.stamp ? ` taken ${new Date(f.stamp * 1000).toLocaleTimeString()}` : "") +
    (age === null ? "" : `, ${age.toFixed(1)} s old`) +
    ` (on the clone ${Number.isFinite(f.ageMs) ? f.ageMs.toFixed(0) + " ms after it was taken" : "-"}; read in ${f.readMs} ms)`;
}

function connect() {
  const link = document.getElementById("link");
  const source = new EventSource("/events");
  source.addEventListener("open", () => { link.textContent = "live"; link.className = "link up"; });
  source.addEventListener("error", () => {
    // The browser retries by itself, unless the server refused the stream (401: a dashboard
    // restarted since this page opened its session).
    const closed = source.readyState === EventSource.CLOSED;
    link.textContent = closed ? "disconnected: open the URL ccrp dashboard printed" : "reconnecting…";
    link.className = "link down";
  });
  source.addEventListener("fleet", (e) => renderFleet(JSON.parse(e.data)));
  source.addEventListener("action", (e) => renderAction(JSON.parse(e.data)));
  // Commands another page sent (this page's own come back in their POST's answer).
  source.addEventListener("teleop", (e) => { if (!driving) showDrive(JSON.parse(e.data)); });
}

document.addEventListener("DOMContentLoaded", () => {
  document.getElementById("logout").addEventListener("click", logout);
  const size = document.getElementById("scale-size");
  size.addEventListener("input", () => { size.dataset.touched = "1"; });
  document.getElementById("scale-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const n = parseInt(size.value, 10);
    if (confirm(`Scale the fleet to ${n} clones (= ccrp fleet scale ${n})?`)) {
      delete size.dataset.touched;
      act("fleet-scale", {size: n});
    }
  });
  document.querySelectorAll("#teleop-pad button").forEach((b) => {
    b.addEventListener("click", () => drive(b.dataset.drive));
  });
  document.getElementById("teleop-robot").addEventListener("change", (e) => e.target.blur());
  document.getElementById("camera-robot").addEventListener("change", (e) => { e.target.blur(); cameraChanged(); });
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) releaseKeys();  // a tab switched away from gets no keyup: stop the robot now
    if (!document.hidden && !cameraTimer && !cameraReading && document.getElementById("camera-robot").value) readCamera();
  });
  window.addEventListener("blur", releaseKeys);  // another window took the keyboard: stop the robot
  setInterval(showCameraAge, 500);
  document.addEventListener("keydown", (e) => {
    const tag = e.target.tagName;
    if (tag === "INPUT" || tag === "SELECT" || tag === "TEXTAREA" || e.ctrlKey || e.metaKey || e.altKey) return;
    const name = KEYS[e.key.length === 1 ? e.key.toLowerCase() : e.key];
    if (!name || !document.getElementById("teleop-robot").value) return;
    e.preventDefault();  // the arrows drive, they do not scroll the page
    holdKey(name);
  });
  document.addEventListener("keyup", (e) => {
    const name = KEYS[e.key.length === 1 ? e.key.toLowerCase() : e.key];
    if (name && name !== "stop" && document.getElementById("teleop-robot").value
        && !["INPUT", "SELECT", "TEXTAREA"].includes(e.target.tagName)) releaseKeys();  // a key let go stops the robot
  });
  connect();
});

// companion status page: polls /api/v1/page/state, shows the MJPEG stream, drives missions.
// Plain JS, no build step, no external files. Every request carries the token (if one is set).
"use strict";
const $ = (id) => document.getElementById(id);
const tokenInput = $("token");
tokenInput.value = sessionStorage.getItem("companion-token") || "";
tokenInput.addEventListener("change", () => sessionStorage.setItem("companion-token", tokenInput.value.trim()));

function headers(extra) {
  const h = Object.assign({}, extra || {});
  const t = tokenInput.value.trim();
  if (t) h["Authorization"] = "Bearer " + t;
  return h;
}
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
function text(v, digits) {
  if (v === null || v === undefined) return "-";
  return typeof v === "number" && digits !== undefined ? v.toFixed(digits) : String(v);
}
function rows(table, pairs) {
  table.replaceChildren(...pairs.map(([k, v]) => {
    const tr = document.createElement("tr");
    const a = document.createElement("td"); a.textContent = k;
    const b = document.createElement("td"); b.textContent = v;
    tr.append(a, b); return tr;
  }));
}
function message(msg, isError) {
  const m = $("message"); m.textContent = msg; m.className = "small" + (isError ? " error" : "");
}
async function api(method, path, body, extraHeaders) {
  const r = await fetch(path, {method, body, headers: headers(extraHeaders)});
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  return {status: r.status, ok: r.ok, data};
}

// ------------------------------------------------------------------ live image (MJPEG parsed from fetch)
function indexOf(buf, pat, from) {
  outer: for (let i = from || 0; i <= buf.length - pat.length; i++) {
    for (let j = 0; j < pat.length; j++) if (buf[i + j] !== pat[j]) continue outer;
    return i;
  }
  return -1;
}
let lastUrl = null;
function showJpeg(bytes) {
  const img = $("video");
  const url = URL.createObjectURL(new Blob([bytes], {type: "image/jpeg"}));
  img.onload = () => { if (lastUrl && lastUrl !== url) URL.revokeObjectURL(lastUrl); lastUrl = url; };
  img.src = url;
  img.dataset.frames = String(Number(img.dataset.frames || 0) + 1);
}
async function videoLoop() {
  const CRLF2 = [13, 10, 13, 10];
  for (;;) {
    try {
      const r = await fetch("/api/v1/video.mjpeg", {headers: headers()});
      if (r.status === 404) { $("video-info").textContent = "no video (video.enabled = false)"; await sleep(5000); continue; }
      if (!r.ok) { $("video-info").textContent = "video: HTTP " + r.status; await sleep(2000); continue; }
      const reader = r.body.getReader();
      let buf = new Uint8Array(0);
      for (;;) {
        const {value, done} = await reader.read();
        if (done) break;
        const next = new Uint8Array(buf.length + value.length);
        next.set(buf); next.set(value, buf.length); buf = next;
        for (;;) {
          const end = indexOf(buf, CRLF2, 0);
          if (end < 0) break;
          const head = new TextDecoder().decode(buf.subarray(0, end));
          const m = /Content-Length:\s*(\d+)/i.exec(head);
          if (!m) { buf = buf.subarray(end + 4); continue; }
          const start = end + 4, len = Number(m[1]);
          if (buf.length < start + len) break;
          showJpeg(buf.slice(start, start + len));
          buf = buf.subarray(start + len);
        }
      }
    } catch (e) { $("video-info").textContent = "video: " + e; }
    await sleep(1000);
  }
}

// ------------------------------------------------------------------ state
function drawMap(st) {
  const cv = $("map"), g = cv.getContext("2d");
  g.clearRect(0, 0, cv.width, cv.height);
  const rack = st.rack || [], traj = st.trajectory_rack_m || [];
  const xs = [], ys = [];
  rack.forEach((p) => { xs.push(p.start[0], p.end[0]); ys.push(p.start[1], p.end[1]); });
  traj.forEach((p) => { xs.push(p[0]); ys.push(p[1]); });
  const pose = st.pose;
  if (pose) { xs.push(pose.rack_m[0]); ys.push(pose.rack_m[1]); }
  if (!xs.length) return;
  const x0 = Math.min(...xs) - 0.5, x1 = Math.max(...xs) + 0.5, y0 = Math.min(...ys) - 0.5, y1 = Math.max(...ys) + 0.5;
  const s = Math.min(cv.width / (x1 - x0), cv.height / (y1 - y0));
  const X = (x) => (x - x0) * s, Y = (y) => cv.height - (y - y0) * s;  // rack y (along the pipes) up
  g.lineCap = "round";
  rack.forEach((p) => {
    g.strokeStyle = "#5b6670"; g.lineWidth = Math.max(2, 2 * p.radius * s);
    g.beginPath(); g.moveTo(X(p.start[0]), Y(p.start[1])); g.lineTo(X(p.end[0]), Y(p.end[1])); g.stroke();
  });
  g.strokeStyle = "#4fc3f7"; g.lineWidth = 2; g.beginPath();
  traj.forEach((p, i) => (i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1]))));
  g.stroke();
  if (pose) {
    const px = X(pose.rack_m[0]), py = Y(pose.rack_m[1]), h = pose.heading_rack_rad;
    g.fillStyle = pose.ok ? "#ffd866" : "#ff7a7a";
    g.beginPath(); g.arc(px, py, 5, 0, 2 * Math.PI); g.fill();
    g.strokeStyle = g.fillStyle; g.beginPath(); g.moveTo(px, py);
    g.lineTo(px + 16 * Math.cos(h), py - 16 * Math.sin(h)); g.stroke();
  }
}
function render(st) {
  const v = st.vehicle || {}, link = st.link || {};
  const ls = $("link-state");
  ls.textContent = (link.health || "-") + " " + (link.autopilot || "");
  ls.className = "pill " + (link.health === "autopilot-ok" ? "ok" : "bad");
  rows($("vehicle"), [["mode", text(v.mode)], ["armed", v.armed ? "ARMED" : "disarmed"],
    ["battery", text(v.battery_v, 2) + " V  " + text(v.battery_pct) + " %"], ["height", text(v.height_m, 2) + " m"],
    ["EKF flags", v.ekf_flags === null || v.ekf_flags === undefined ? "-" : "0x" + v.ekf_flags.toString(16) + " " + (v.ekf || []).join(", ")],
    ["camera", text((st.camera || {}).state)]]);
  const p = st.pose;
  rows($("pose"), p ? [["source", p.source + (p.ok ? "" : " (not ok)")], ["NED", p.ned_m.map((x) => x.toFixed(2)).join(", ") + " m"],
    ["yaw", text(p.yaw_deg, 1) + " deg"], ["rack x, y, z", p.rack_m.map((x) => x.toFixed(2)).join(", ") + " m"]] : [["pose", "none"]]);
  const m = st.mission || {}, steps = st.mission_steps || [];
  $("mission-state").textContent = (m.name ? m.name + ": " : "") + (m.state || "none");
  const done = steps.filter((s) => s.status !== "pending" && s.status !== "active").length;
  $("mission-progress").style.width = steps.length ? (100 * done / steps.length).toFixed(0) + "%" : "0";
  $("mission-progress").dataset.done = String(done);
  $("mission-steps").replaceChildren(...steps.map((s) => {
    const li = document.createElement("li");
    li.className = s.status; li.textContent = `${s.action} ${s.id}: ${s.status}` + (s.seconds !== null ? ` (${s.seconds} s)` : "");
    return li;
  }));
  const sf = st.safety || {};
  $("safety-action").textContent = sf.action || "-";
  $("safety-action").className = "pill " + (sf.action === "none" ? "ok" : "warn");
  $("faults").replaceChildren(...(sf.faults || []).map((f) => {
    const li = document.createElement("li"); li.textContent = Object.entries(f).map(([k, x]) => k + "=" + x).join(" "); return li;
  }));
  $("log").textContent = (st.log || []).join("\n");
  const vid = st.video || {};
  $("video-info").textContent = vid.enabled ? `RTP H.264 to ${vid.destination}, ${vid.size.join("x")}, ${vid.encoded} frames sent, SDP ${vid.sdp}` : "video off";
  drawMap(st);
}
async function stateLoop() {
  for (;;) {
    try {
      const r = await api("GET", "/api/v1/page/state");
      if (r.ok) render(r.data);
      else { $("link-state").textContent = "HTTP " + r.status + (r.data ? ": " + r.data.error : ""); $("link-state").className = "pill bad"; }
    } catch (e) { $("link-state").textContent = "daemon unreachable"; $("link-state").className = "pill bad"; }
    await sleep(500);
  }
}

// ------------------------------------------------------------------ missions
async function refreshMissions() {
  const r = await api("GET", "/api/v1/missions");
  if (!r.ok) return;
  $("missions").replaceChildren(...r.data.missions.map((m) => {
    const li = document.createElement("li");
    li.dataset.id = m.id;
    li.textContent = `${m.id} (${m.name || "?"}, ${m.actions ?? "?"} actions) `;
    const b = document.createElement("button"); b.textContent = "Start"; b.className = "start";
    b.onclick = async () => {
      const s = await api("POST", `/api/v1/missions/${encodeURIComponent(m.id)}/start`);
      message(s.ok ? `mission ${m.id} started` : `start refused (${s.status}): ${s.data && s.data.error}`, !s.ok);
    };
    li.append(b); return li;
  }));
}
$("btn-upload").onclick = async () => {
  const f = $("mission-file").files[0];
  if (!f) { message("choose a mission file first", true); return; }
  const r = await api("POST", "/api/v1/missions?name=" + encodeURIComponent(f.name), await f.arrayBuffer(),
    {"Content-Type": "application/xml"});
  if (r.ok) { message(`uploaded ${r.data.id}` + (r.data.replaced ? " (replaced)" : ""), false); refreshMissions(); }
  else message(`upload refused (${r.status}): ${r.data && r.data.error}`, true);
};
for (const action of ["pause", "resume", "abort"]) {
  $("btn-" + action).onclick = async () => {
    const r = await api("POST", "/api/v1/mission/" + action);
    message(r.ok ? `${action}: ok` : `${action} refused (${r.status}): ${r.data && r.data.error}`, !r.ok);
  };
}
setInterval(refreshMissions, 2000);
refreshMissions();
stateLoop();
videoLoop();

"""The live view's one page (:mod:`swarmrec.services.live_view`): HTML, CSS and plain
JavaScript in one string, so nothing is built and nothing is fetched from outside.

The page reads ``/api/state`` every two seconds and listens to ``/api/events``
(server-sent events) for loop closures, query reports, fusion decisions and
members joining or leaving; both carry the token of the page's own address.
A panel of a method the swarm does not run stays hidden (``data-method``:
constellations, dvpr, slam, landmarks, and closures for the two place methods).
Elements a test looks for carry ``data-*`` attributes (``data-member``,
``data-closure``, ``data-shard``, ``data-owner``, ``data-message``, ``data-slam``,
``data-trajectory``, ``data-separator``).
"""

from __future__ import annotations

__all__ = ["PAGE"]

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>swarmrec live view</title>
<style>
  body { font: 14px/1.4 system-ui, sans-serif; margin: 0; background: #f6f7f9; color: #1d2330; }
  header { background: #1d2330; color: #fff; padding: 10px 18px; display: flex; gap: 24px;
           align-items: baseline; flex-wrap: wrap; }
  header h1 { font-size: 18px; margin: 0; }
  header .fig { font-size: 13px; opacity: .85; }
  header .fig b { font-size: 16px; }
  main { display: grid; grid-template-columns: repeat(auto-fit, minmax(380px, 1fr)); gap: 14px;
         padding: 14px; }
  section { background: #fff; border: 1px solid #dde1e7; border-radius: 6px; padding: 10px 14px; }
  h2 { font-size: 14px; margin: 0 0 8px; text-transform: uppercase; letter-spacing: .04em; color: #556; }
  table { border-collapse: collapse; width: 100%; font-size: 13px; }
  th, td { text-align: left; padding: 2px 6px; border-bottom: 1px solid #eef0f3; }
  td.n { text-align: right; font-variant-numeric: tabular-nums; }
  .gone td { color: #b3261e; text-decoration: line-through; }
  .dot { display: inline-block; width: 8px; height: 8px; border-radius: 50%; background: #2e7d32; }
  .gone .dot { background: #b3261e; }
  .bar { display: flex; align-items: center; gap: 8px; font-size: 13px; margin: 2px 0; }
  .bar .label { width: 130px; overflow: hidden; text-overflow: ellipsis; white-space: nowrap; }
  .bar .track { flex: 1; background: #eef0f3; height: 12px; border-radius: 2px; }
  .bar .fill { background: #3b6fd4; height: 12px; border-radius: 2px; }
  .bar .value { width: 90px; text-align: right; font-variant-numeric: tabular-nums; }
  .new { animation: flash 1.5s ease-out; }
  @keyframes flash { from { background: #fff3b0; } to { background: transparent; } }
  #status { font-size: 12px; }
  .err { color: #ffb4ab; }
  .muted { color: #889; font-size: 12px; }
  .scroll { max-height: 360px; overflow-y: auto; }
  [hidden] { display: none !important; }
  svg.map { width: 100%; height: 360px; background: #fbfcfd; border: 1px solid #eef0f3; }
  .legend span { margin-right: 12px; font-size: 12px; }
</style>
</head>
<body>
<header>
  <h1>swarmrec <span id="swarm">…</span></h1>
  <span class="fig"><b id="n-members">0</b> members</span>
  <span class="fig" data-method="closures"><b id="n-closures">0</b> loop closures</span>
  <span class="fig" data-method="closures"><span id="version-label">placement</span>
    <b id="version">-</b></span>
  <span class="fig" id="status">connecting…</span>
</header>
<main>
  <section><h2>Members</h2>
    <div class="scroll"><table><thead><tr><th></th><th>service</th><th>robot</th><th>groups</th>
      <th class="n">stored</th></tr></thead><tbody id="members"></tbody></table></div></section>
  <section data-method="closures"><h2>Loop closures, newest first</h2>
    <div class="scroll"><table><thead><tr><th>robot</th><th>frame</th><th>with robot</th><th>frame</th>
      <th class="n">score</th><th class="n">objects</th></tr></thead>
      <tbody id="closures"></tbody></table></div></section>
  <section data-method="constellations"><h2>Shard load (partial queries)</h2><div id="load"></div>
    <h2 style="margin-top:12px">Placement history</h2><div id="placements" class="muted"></div></section>
  <section data-method="constellations"><h2>Loop-closure funnel</h2><div id="funnel"></div>
    <p class="muted">Counted from the query reports this page's gateway has seen since it started.</p>
  </section>
  <section data-method="dvpr"><h2>Cluster owner load (place queries)</h2><div id="owners"></div>
    <h2 style="margin-top:12px">Cluster table history</h2><div id="tables" class="muted"></div></section>
  <section data-method="dvpr"><h2>Place-query funnel</h2><div id="place-funnel"></div>
    <p class="muted">Counted from the full-image place reports this page's gateway has seen.</p></section>
  <section data-method="slam"><h2>SLAM team</h2>
    <table><thead><tr><th>robot</th><th>solve</th><th>state</th><th>stage</th><th class="n">iteration</th>
      <th>converged</th></tr></thead><tbody id="slam"></tbody></table></section>
  <section data-method="slam"><h2>Trajectories and where the maps join</h2>
    <svg class="map" id="map" viewBox="0 0 100 100" preserveAspectRatio="xMidYMid meet"></svg>
    <div class="legend muted" id="legend"></div>
    <p class="muted">Each robot's estimate (lines: poses, dots: objects); rings: separators, the
      vertices a robot shares with another robot's map (the inter-robot loop closures).</p></section>
  <section><h2>Bytes between robots, by message</h2><div id="bytes"></div></section>
  <section data-method="landmarks"><h2>Fusion decisions</h2>
    <p class="muted"><b id="n-fusion">0</b> updates heard (a robot's decision after each view it
      folded in); the newest:</p>
    <table><thead><tr><th>robot</th><th>round</th><th>class</th><th>heard all</th></tr></thead>
      <tbody id="fusion"></tbody></table></section>
</main>
<script>
"use strict";
const token = new URLSearchParams(location.search).get("token") || "";
const q = "?token=" + encodeURIComponent(token);
const $ = (id) => document.getElementById(id);
const gone = new Set();
let closuresShown = new Set();

function text(tag, value, cls) {
  const el = document.createElement(tag);
  el.textContent = value;
  if (cls) el.className = cls;
  return el;
}
function bars(target, entries, attr, fmt) {
  const box = $(target);
  box.replaceChildren();
  const top = Math.max(1, ...entries.map((e) => e[1]));
  for (const [name, value] of entries) {
    const row = document.createElement("div");
    row.className = "bar";
    row.dataset[attr] = name;
    const track = document.createElement("div");
    track.className = "track";
    const fill = document.createElement("div");
    fill.className = "fill";
    fill.style.width = (100 * value / top).toFixed(1) + "%";
    track.append(fill);
    row.append(text("span", name, "label"), track, text("span", fmt(value), "value"));
    box.append(row);
  }
  if (!entries.length) box.append(text("p", "nothing yet", "muted"));
}
function closureRow(c, fresh) {
  const key = [c.query_robot, c.query_frame, c.match_robot, c.match_frame].join("/");
  if (closuresShown.has(key)) return null;
  closuresShown.add(key);
  const tr = document.createElement("tr");
  tr.dataset.closure = key;
  if (fresh) tr.className = "new";
  for (const v of [c.query_robot, c.query_frame, c.match_robot, c.match_frame]) tr.append(text("td", v));
  tr.append(text("td", c.score.toFixed(3), "n"), text("td", c.n_matched, "n"));
  return tr;
}
function addClosure(c, fresh) {
  const tr = closureRow(c, fresh);
  if (!tr) return;
  const body = $("closures");
  body.prepend(tr);
  while (body.children.length > 50) body.lastChild.remove();
}
const COLOURS = ["#3b6fd4", "#d4553b", "#2e9d5a", "#9b4fd1", "#d49a1f", "#1fa3b3", "#c2408a", "#6d7a2b"];
const SVG = "http://www.w3.org/2000/svg";
function svg(tag, attrs) {
  const el = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  return el;
}
function drawMap(robots) {
  const map = $("map");
  map.replaceChildren();
  const all = robots.flatMap((r) => [...r.poses, ...r.objects]);
  if (!all.length) return;
  const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
  const x0 = Math.min(...xs), y0 = Math.min(...ys);
  const span = Math.max(Math.max(...xs) - x0, Math.max(...ys) - y0, 1e-9);
  // y up, as a map is read; a 5 % margin.
  const at = (p) => [5 + 90 * (p[0] - x0) / span, 95 - 90 * (p[1] - y0) / span];
  const legend = $("legend");
  legend.replaceChildren();
  for (const r of robots) {
    const colour = COLOURS[r.robot % COLOURS.length];
    const line = svg("polyline", { points: r.poses.map((p) => at(p).join(",")).join(" "), fill: "none",
                                   stroke: colour, "stroke-width": 0.5 });
    line.dataset.trajectory = String(r.robot);
    map.append(line);
    for (const o of r.objects) {
      const [x, y] = at(o);
      map.append(svg("circle", { cx: x, cy: y, r: 0.6, fill: colour, opacity: 0.6 }));
    }
    for (const sep of r.separators) {
      const [x, y] = at(sep.at);
      const ring = svg("circle", { cx: x, cy: y, r: 1.4, fill: "none", stroke: "#1d2330",
                                   "stroke-width": 0.3 });
      ring.dataset.separator = r.robot + "-" + sep.with;
      ring.append(svg("title", {}));
      ring.lastChild.textContent = "robot " + r.robot + " shares this with robot " + sep.with;
      map.append(ring);
    }
    const key = text("span", "robot " + r.robot + ": " + r.poses.length + " poses, " +
                     r.separators.length + " separators");
    key.style.color = colour;
    legend.append(key);
  }
}
function renderSlam(robots) {
  const body = $("slam");
  body.replaceChildren();
  for (const r of robots) {
    const tr = document.createElement("tr");
    tr.dataset.slam = String(r.robot);
    tr.dataset.state = r.state;
    tr.append(text("td", r.robot), text("td", r.solve ?? ""), text("td", r.error ? r.error : r.state),
              text("td", r.stage ?? ""), text("td", r.iteration ?? "", "n"),
              text("td", r.converged ? "yes" : (r.state === "done" ? "no" : "")));
    body.append(tr);
  }
  drawMap(robots.filter((r) => r.poses.length));
}
function showMethods(s) {
  const kinds = new Set(s.members.map((m) => m.kind));
  const runs = {
    constellations: kinds.has("index-shard") || s.funnel.queries > 0,
    dvpr: kinds.has("place-owner") || s.place_funnel.queries > 0,
    slam: kinds.has("slam") || s.slam.length > 0,
    landmarks: kinds.has("fusion") || s.fusion.length > 0,
  };
  runs.closures = runs.constellations || runs.dvpr;
  for (const el of document.querySelectorAll("[data-method]")) el.hidden = !runs[el.dataset.method];
}
function render(s) {
  $("swarm").textContent = s.swarm;
  $("n-members").textContent = s.members.length;
  $("n-closures").textContent = s.closures_total;
  const p = s.placement || {};
  $("version").textContent = p.version === undefined || p.version < 0 ? "-" :
    p.version + (p.settled ? " (settled)" : " (moving)");
  const table = s.cluster_table || {};
  const clusters = !(p.version >= 0) && table.version >= 0;
  $("version-label").textContent = clusters ? "cluster table" : "placement";
  if (clusters) $("version").textContent = "v" + table.version;
  const body = $("members");
  body.replaceChildren();
  for (const m of s.members) {
    const name = m.kind + "-" + m.robot;
    const tr = document.createElement("tr");
    tr.dataset.member = name;
    if (gone.has(name)) tr.className = "gone";
    const dot = document.createElement("td");
    dot.append(text("span", "", "dot"));
    tr.append(dot, text("td", m.kind), text("td", m.robot), text("td", m.groups.join(" ")),
              text("td", m.stored, "n"));
    body.append(tr);
  }
  for (const name of s.left) {
    if (s.members.some((m) => m.kind + "-" + m.robot === name)) continue;
    const tr = document.createElement("tr");
    tr.dataset.member = name;
    tr.className = "gone";
    const dot = document.createElement("td");
    dot.append(text("span", "", "dot"));
    tr.append(dot, text("td", name), text("td", ""), text("td", "gone"), text("td", "", "n"));
    body.append(tr);
  }
  for (const c of s.closures) addClosure(c, false);
  bars("load", Object.entries(s.shard_load).map(([r, v]) => ["shard " + r, v]), "shard",
       (v) => v.toFixed(0));
  $("placements").textContent = (p.history || []).map(([t, v]) =>
    "v" + v + " at " + new Date(t * 1000).toLocaleTimeString()).join(" → ") || "no placement yet";
  const f = s.funnel;
  bars("funnel", [["queries", f.queries], ["queried", f.queried], ["candidates", f.candidates],
                  ["verified pairs", f.verified_pairs], ["closures", f.closures]], "stage",
       (v) => v.toFixed(0));
  bars("owners", Object.entries(s.owner_load).map(([r, v]) => ["owner " + r, v]), "owner",
       (v) => v.toFixed(0));
  $("tables").textContent = (table.history || []).map(([when, v]) =>
    "v" + v + " at " + new Date(when * 1000).toLocaleTimeString()).join(" → ") || "no cluster table yet";
  const pf = s.place_funnel;
  bars("place-funnel", [["place queries", pf.queries], ["owner answered", pf.answered],
                        ["matched", pf.matched], ["verified", pf.verified], ["closures", pf.closures]],
       "stage", (v) => v.toFixed(0));
  renderSlam(s.slam);
  showMethods(s);
  bars("bytes", Object.entries(s.bytes_by_message), "message", (v) => (v / 1024).toFixed(1) + " kB");
  $("n-fusion").textContent = s.fusion_total;
  const fusion = $("fusion");
  fusion.replaceChildren();
  for (const d of s.fusion.slice().reverse()) {
    const tr = document.createElement("tr");
    tr.dataset.fusion = [d.robot, d.round, d.decision, d.heard_all ? 1 : 0].join("/");
    tr.append(text("td", d.robot), text("td", d.round), text("td", d.decision),
              text("td", d.heard_all ? "yes" : "no"));
    fusion.append(tr);
  }
  $("status").textContent = s.error ? s.error : "up " + Math.round(s.up_s) + " s, updated " +
    new Date(s.time * 1000).toLocaleTimeString();
  $("status").className = s.error ? "err" : "";
}
async function poll() {
  try {
    const reply = await fetch("/api/state" + q, { cache: "no-store" });
    if (!reply.ok) throw new Error(reply.status + " " + (await reply.text()));
    render(await reply.json());
  } catch (e) {
    $("status").textContent = "cannot read the swarm: " + e.message;
    $("status").className = "err";
  }
}
function listen() {
  const events = new EventSource("/api/events" + q);
  events.addEventListener("closure", (e) => {
    addClosure(JSON.parse(e.data), true);
    $("n-closures").textContent = Number($("n-closures").textContent) + 1;
  });
  events.addEventListener("member", (e) => {
    const m = JSON.parse(e.data);
    if (m.alive) gone.delete(m.name); else gone.add(m.name);
    const row = document.querySelector('[data-member="' + m.name + '"]');
    if (row) row.className = m.alive ? "" : "gone";
  });
  events.onerror = () => { $("status").textContent = "event stream lost; retrying"; };
}
poll();
listen();
setInterval(poll, 2000);
</script>
</body>
</html>
"""

// The dashboard's page: plain HTML, CSS and JavaScript, no build step.
// "#/" lists the envs (polling /api/envs every second); "#/envs/<id>" shows
// one env's frames from the /api/frames event stream beside its table.
#include "mll/service/dashboard.h"

namespace mll::service {
namespace {

constexpr char kPage[] = R"html(<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>Multi Lunar Lander</title>
<style>
  [hidden] { display: none !important; }
  body { font: 14px/1.4 system-ui, sans-serif; margin: 0; background: #111; color: #ddd; }
  header { padding: 10px 16px; background: #1c1c28; display: flex; gap: 16px; align-items: baseline; }
  header h1 { font-size: 18px; margin: 0; }
  header a { color: #9ab; }
  main { padding: 12px 16px; }
  table { border-collapse: collapse; }
  th, td { padding: 4px 10px; text-align: left; border-bottom: 1px solid #333; }
  th { color: #999; font-weight: 600; }
  tr.env:hover { background: #222; cursor: pointer; }
  a { color: #8cf; }
  .muted { color: #888; }
  .landed { color: #5d5; } .crashed, .out_of_bounds, .aborted { color: #f66; } .truncated { color: #db5; }
  .swatch { display: inline-block; width: 10px; height: 10px; border-radius: 2px; margin-right: 4px; }
  #view { display: flex; gap: 20px; flex-wrap: wrap; align-items: flex-start; }
  #frame { width: 600px; height: 400px; background: #000; border: 1px solid #333; image-rendering: auto; }
  #login { display: none; } #login input { width: 320px; }
  .error { color: #f88; }
</style>
</head>
<body>
<header><h1>Multi Lunar Lander</h1><a href="#/">environments</a><span id="status" class="muted"></span></header>
<main>
  <form id="login"><p>This server needs a token. Environments are shown only to the token that created them.</p>
    <input id="token" type="password" placeholder="token" autocomplete="off"> <button>Show my environments</button>
    <p id="login-error" class="error"></p></form>
  <section id="list"><table><thead><tr><th>name</th><th>landers</th><th>episode</th><th>step</th>
    <th>returns so far</th><th>outcomes</th></tr></thead><tbody id="envs"></tbody></table>
    <p id="empty" class="muted">No environment is hosted.</p></section>
  <section id="view" hidden><div><img id="frame" alt="live frame">
    <p class="muted"><span id="fps">connecting</span> · <span id="frames">0</span> frames</p></div>
    <div><h2 id="view-name"></h2><table><thead><tr><th>lander</th><th>return</th><th>outcome</th></tr></thead>
      <tbody id="landers"></tbody></table><p id="view-status" class="muted"></p></div></section>
</main>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
let stream = null, timer = null, frameCount = 0, frameTimes = [];

function colour(i) {  // AgentColor of the renderer, for the swatches.
  if (i === 0) return "rgb(128,102,230)";
  let r = 0; for (let b = 0; b < 5; ++b) r |= ((i >> b) & 1) << (4 - b);
  const h = ((252 + 360 * r / 32) % 360) / 60, v = 230 / 255, c = v * (102 / 230);
  const x = c * (1 - Math.abs(h % 2 - 1)), m = v - c;
  const rgb = [[c,x,0],[x,c,0],[0,c,x],[0,x,c],[x,0,c],[c,0,x]][Math.floor(h)];
  return "rgb(" + rgb.map((u) => Math.round((u + m) * 255)).join(",") + ")";
}
function text(tag, value, cls) {
  const e = document.createElement(tag); e.textContent = value; if (cls) e.className = cls; return e;
}
async function fetchEnvs() {
  const res = await fetch("/api/envs", {cache: "no-store"});
  if (res.status === 401) { $("login").style.display = "block"; throw new Error("token needed"); }
  if (!res.ok) throw new Error("HTTP " + res.status);
  $("login").style.display = "none";
  return (await res.json()).envs;
}
function showList(envs) {
  const body = $("envs"); body.replaceChildren();
  for (const env of envs) {
    const tr = document.createElement("tr"); tr.className = "env"; tr.dataset.name = env.name;
    const link = text("a", env.name); link.href = "#/" + env.name;
    const name = document.createElement("td"); name.appendChild(link); tr.appendChild(name);
    tr.appendChild(text("td", env.landers)); tr.appendChild(text("td", env.episode));
    tr.appendChild(text("td", env.step));
    tr.appendChild(text("td", env.returns.map((r) => r.toFixed(1)).join("  ")));
    const outcomes = document.createElement("td");
    env.outcomes.forEach((o, i) => {
      const s = text("span", (i ? " " : "") + (o === "none" ? "·" : o), o); outcomes.appendChild(s);
    });
    tr.appendChild(outcomes);
    tr.onclick = () => { location.hash = "#/" + env.name; };
    body.appendChild(tr);
  }
  $("empty").hidden = envs.length > 0;
}
function showLanders(env) {
  const body = $("landers"); body.replaceChildren();
  env.returns.forEach((r, i) => {
    const tr = document.createElement("tr");
    const id = document.createElement("td"); const sw = text("span", ""); sw.className = "swatch";
    sw.style.background = colour(i); id.appendChild(sw); id.appendChild(document.createTextNode("lander_" + i));
    tr.appendChild(id); tr.appendChild(text("td", r.toFixed(1)));
    tr.appendChild(text("td", env.outcomes[i] === "none" ? "flying" : env.outcomes[i], env.outcomes[i]));
    body.appendChild(tr);
  });
  $("view-status").textContent = "episode " + env.episode + ", step " + env.step;
}
async function refresh() {
  const route = location.hash.replace(/^#\/?/, "");
  try {
    const envs = await fetchEnvs();
    $("status").textContent = envs.length + " environment" + (envs.length === 1 ? "" : "s");
    if (route) {
      const env = envs.find((e) => e.name === route);
      if (env) showLanders(env); else $("view-status").textContent = "this environment is gone";
    } else {
      showList(envs);
    }
  } catch (e) { $("status").textContent = e.message; }
}
function openStream(name) {
  if (stream) stream.close();
  frameCount = 0; frameTimes = [];
  stream = new EventSource("/api/frames?name=" + encodeURIComponent(name));
  stream.addEventListener("frame", (ev) => {
    $("frame").src = "data:image/png;base64," + ev.data;
    $("frame").dataset.version = ev.lastEventId;
    frameCount += 1; $("frames").textContent = frameCount;
    const now = performance.now(); frameTimes.push(now);
    while (frameTimes.length && now - frameTimes[0] > 2000) frameTimes.shift();
    $("fps").textContent = (frameTimes.length / 2).toFixed(1) + " frames/s";
  });
  stream.addEventListener("gone", () => {
    stream.close(); stream = null; $("fps").textContent = "the environment is gone";
  });
  stream.onerror = () => { $("fps").textContent = "reconnecting"; };
}
function route() {
  const name = location.hash.replace(/^#\/?/, "");
  $("list").hidden = !!name; $("view").hidden = !name;
  if (name) { $("view-name").textContent = name; openStream(name); }
  else if (stream) { stream.close(); stream = null; }
  refresh();
}
$("login").onsubmit = (ev) => {
  ev.preventDefault();
  document.cookie = "mll_token=" + encodeURIComponent($("token").value) + "; path=/; SameSite=Strict";
  $("token").value = ""; route();
};
window.addEventListener("hashchange", route);
route();
timer = setInterval(refresh, 1000);
</script>
</body>
</html>
)html";

}  // namespace

const char* DashboardPage() { return kPage; }

}  // namespace mll::service

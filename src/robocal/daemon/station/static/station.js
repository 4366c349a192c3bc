// robocal station: confirmations, live refresh over Server-Sent Events, the residual plot.
// No framework and no external file: the station works offline on the cell network.
"use strict";

(function () {
  const body = document.body;

  // Every state-changing form names what will happen to the robot and asks first.
  document.addEventListener("submit", (ev) => {
    const form = ev.target;
    let msg = form.dataset.confirm;
    if (!msg) return;
    const model = form.querySelector("select[name=model]");
    const plan = form.querySelector("input[name=plan]");
    msg = msg.replace("{model}", model ? model.value : "").replace("{plan}", plan ? plan.value : "");
    if (!window.confirm(msg)) ev.preventDefault();
  });

  // --- live refresh: the server renders, the page swaps the fragment in --------------------
  const liveUrl = body.dataset.live;
  let busy = false, again = false;
  async function refresh() {
    if (busy) { again = true; return; }
    busy = true;
    try {
      const r = await fetch(liveUrl, { credentials: "same-origin", cache: "no-store" });
      if (r.ok) {
        const d = await r.json();
        const live = document.getElementById("live");
        const box = document.getElementById("bannerbox");
        if (box && d.banner !== undefined && box.innerHTML !== d.banner) box.innerHTML = d.banner;
        if (live && live.innerHTML !== d.live) swap(live, d.live);
        // the report appears once, when it has been written after the fit (not reloaded on
        // every event); the "rendering" note before it is replaced
        const rep = document.getElementById("reportbox");
        const placeholder = rep && rep.querySelector("[data-rendering]");
        if (rep && d.report && (!rep.firstElementChild || placeholder) && rep.innerHTML !== d.report) {
          rep.innerHTML = d.report;
        }
        if (body.dataset.page === "campaign") plot();
      }
    } catch (e) { /* the daemon restarting: the next event or reconnect retries */ }
    busy = false;
    if (again) { again = false; refresh(); }
  }

  // Keep what the operator is typing: the actions are left alone while focused, unless the
  // campaign's state changed (then the old buttons would be wrong).
  function swap(live, html) {
    const actions = document.getElementById("actions");
    const focused = actions && actions.contains(document.activeElement);
    if (focused) {
      const tmp = document.createElement("div");
      tmp.innerHTML = html;
      const fresh = tmp.querySelector("#actions");
      if (fresh && fresh.dataset.key === actions.dataset.key) {
        fresh.replaceWith(actions);
        live.replaceChildren(...tmp.childNodes);
        return;
      }
    }
    live.innerHTML = html;
  }

  if (liveUrl && window.EventSource) {
    const es = new EventSource("/events?after=" + encodeURIComponent(body.dataset.seq || "0"));
    for (const kind of ["state", "pose", "retry", "warmup", "fit", "compensation", "report",
                        "log"]) {
      es.addEventListener(kind, refresh);
    }
    es.onopen = () => { body.dataset.sse = "open"; };
  }

  // --- residual plot: SVG, log scale in mm ------------------------------------------------
  const NS = "http://www.w3.org/2000/svg";
  let plotBusy = false;
  function el(name, attrs, text) {
    const n = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
    if (text !== undefined) n.textContent = text;
    return n;
  }
  // At most one plot fetch a second (a 10,000-pose campaign sends every pose an event),
  // and always one after the last event.
  let plotLast = 0, plotTimer = null;
  async function plot() {
    const box = document.getElementById("plot");
    if (!box) return;
    const wait = plotLast + 1000 - Date.now();
    if (plotBusy || wait > 0) {
      if (!plotTimer) plotTimer = setTimeout(() => { plotTimer = null; plot(); }, Math.max(wait, 200));
      return;
    }
    plotBusy = true;
    plotLast = Date.now();
    try {
      const r = await fetch(box.dataset.points, { credentials: "same-origin", cache: "no-store" });
      if (r.ok) draw(box, await r.json());
    } catch (e) { /* next event retries */ }
    plotBusy = false;
  }
  function draw(box, d) {
    const W = 1000, H = 260, L = 60, R = 10, T = 24, B = 30;
    const series = [];
    const cal = d.spread.filter((p) => !p[2] && p[1] > 0), held = d.spread.filter((p) => p[2] && p[1] > 0);
    series.push({ cls: "spread", label: "reading spread (calibration poses)", pts: cal });
    series.push({ cls: "heldout", label: "reading spread (held-out poses)", pts: held });
    let i = 0;
    for (const [name, pts] of Object.entries(d.models)) {
      series.push({ cls: "m" + Math.min(i++, 1), label: "|measured − " + name + "|", pts: pts.filter((p) => p[1] > 0) });
    }
    const all = series.flatMap((s) => s.pts);
    const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, preserveAspectRatio: "none", "aria-hidden": "true" });
    if (!all.length) {
      svg.appendChild(el("text", { x: L, y: H / 2 }, "no pose measured yet"));
      box.replaceChildren(svg);
      box.dataset.n = "0";
      return;
    }
    const xmax = Math.max(1, ...all.map((p) => p[0]));
    let lo = Math.floor(Math.log10(Math.min(...all.map((p) => p[1]))));
    let hi = Math.ceil(Math.log10(Math.max(...all.map((p) => p[1]))));
    if (hi <= lo) hi = lo + 1;
    const x = (v) => L + (W - L - R) * v / xmax;
    const y = (v) => H - B - (H - B - T) * (Math.log10(v) - lo) / (hi - lo);
    svg.appendChild(el("line", { class: "axis", x1: L, y1: H - B, x2: W - R, y2: H - B }));
    svg.appendChild(el("line", { class: "axis", x1: L, y1: T, x2: L, y2: H - B }));
    for (let k = lo; k <= hi; k++) {
      svg.appendChild(el("text", { x: 4, y: y(10 ** k) + 4 }, String(+(10 ** k).toPrecision(1)) + " mm"));
    }
    svg.appendChild(el("text", { x: W / 2, y: H - 6 }, "pose index (0 – " + xmax + ")"));
    let lx = L + 10;
    for (const s of series) {
      if (!s.pts.length) continue;
      // one path per series: fast with 10,000 poses
      let dpath = "";
      for (const p of s.pts) dpath += `M${x(p[0]).toFixed(1)} ${y(p[1]).toFixed(1)}h4v4h-4z`;
      svg.appendChild(el("path", { class: s.cls, d: dpath }));
      svg.appendChild(el("rect", { class: s.cls, x: lx, y: 8, width: 8, height: 8 }));
      svg.appendChild(el("text", { x: lx + 12, y: 16 }, s.label));
      lx += 12 + 7 * s.label.length + 16;
    }
    box.replaceChildren(svg);
    box.dataset.n = String(d.spread.length);
    box.dataset.models = Object.keys(d.models).join(",");
  }
  if (body.dataset.page === "campaign") plot();
})();

// Live updates: run states, progress and trips from the service's websocket (/api/events, cookie auth).
(function () {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  let socket;
  // a run's page asks for that run: the first event is its current state, so a change between rendering the page
  // and opening the socket is not missed
  const runState = document.getElementById("run-state");
  const query = runState ? "?run=" + runState.dataset.runState : "";
  function connect() {
    socket = new WebSocket(proto + "//" + location.host + "/api/events" + query);
    socket.onmessage = function (message) {
      const event = JSON.parse(message.data);
      if (event.type === "progress") {
        document.querySelectorAll('[data-run-progress="' + event.id + '"]').forEach(function (bar) {
          if (event.duration_s) bar.max = event.duration_s;
          bar.value = event.progress_s;
        });
        document.querySelectorAll('[data-run-progress-text="' + event.id + '"]').forEach(function (text) {
          const of = event.duration_s ? " of " + String(Math.round(event.duration_s * 1000) / 1000) + " s" : "";
          const pct = event.duration_s ? " (" + Math.round(100 * event.progress_s / event.duration_s) + " %)" : "";
          text.textContent = event.progress_s.toFixed(2) + " s" + of + " drive time" + pct;
        });
      } else if (event.type === "trip") {
        document.querySelectorAll('[data-run-trips="' + event.id + '"]').forEach(function (list) {
          const item = document.createElement("li");
          const at = typeof event.t_s === "number" ? " at t = " + event.t_s.toFixed(3) + " s" : "";
          item.textContent = "trip: " + event.reason + at + ": " + event.message;
          list.appendChild(item);
        });
      } else if (event.type === "run") {
        let changed = false;
        document.querySelectorAll('[data-run-state="' + event.id + '"]').forEach(function (el) {
          if (el.textContent !== event.state) { changed = true; el.textContent = event.state; el.className = "state state-" + event.state; }
        });
        // a run that finished or started: reload to show its verdict table, the queue and the rigs
        if (changed || (location.pathname === "/" && !document.querySelector('[data-run="' + event.id + '"]'))) {
          clearTimeout(window.__reload);
          window.__reload = setTimeout(function () { location.reload(); }, 300);
        }
      }
    };
    socket.onclose = function () { setTimeout(connect, 2000); };
  }
  connect();
})();

// The embedded Rerun viewer (templates/_viewer.html): loaded when its section is open, on this run's recording URL
// (absolute: the viewer fetches it itself). The open/closed choice is kept per run for the page's reloads (a run's
// page reloads when the run starts or ends).
(function () {
  const section = document.getElementById("live-view");
  const frame = document.getElementById("live-viewer");
  if (!section || !frame) return;
  const key = "drivebench-live-view-" + section.dataset.run;
  const kept = sessionStorage.getItem(key);
  if (location.hash === "#live-view") section.open = true;
  else if (kept !== null) section.open = kept === "open";      // opened while the run went: stays open when it ends
  window.addEventListener("hashchange", function () { if (location.hash === "#live-view") section.open = true; });
  function load() {
    if (!section.open || frame.getAttribute("src")) return;
    const recording = location.origin + frame.dataset.recording;
    frame.src = "/live/viewer/index.html?url=" + encodeURIComponent(recording) + "&hide_welcome_screen&persist=0";
  }
  section.addEventListener("toggle", function () {
    sessionStorage.setItem(key, section.open ? "open" : "closed");
    load();
  });
  load();
})();

// The drive page: touch joystick, device tilt, keyboard and gamepad; video, mode, recording, stop, health.
// Dependency-free on purpose: the car has no internet, and this is all a phone has to load.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const SEND_MS = 50; // the driver's command rate: keeps control, and keeps the command fresh for the failsafe
  const KEY_STEP = 0.2; // keyboard steering ramps to full lock in a quarter of a second
  const st = { mode: "user", recording: false, control: "free", limit: 0.5, stopLatch: false };
  const pad = { id: null, x: 0, y: 0 };
  const keys = new Set();
  const keySteer = { a: 0 };
  const tilt = { on: false, steer: 0, pitch: 0, pitch0: null };
  let ws = null;
  let retry = 0;
  let wakeLock = null;
  let errorTimer = null;

  const clamp = (v) => Math.max(-1, Math.min(1, v));
  const fmt = (v, d) => (typeof v === "number" && isFinite(v) ? v.toFixed(d) : "–");
  const signed = (v) => (v >= 0 ? "+" : "") + v.toFixed(2);

  // ------------------------------------------------------------------ connection
  function connect() {
    ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/wsDrive");
    ws.onopen = () => { retry = 0; setConn("connected"); };
    ws.onmessage = (ev) => {
      let m;
      try { m = JSON.parse(ev.data); } catch (_) { return; }
      onMessage(m);
    };
    ws.onclose = () => {
      ws = null;
      setConn("disconnected");
      setRole("free");
      setTimeout(connect, Math.min(4000, 500 * ++retry));
    };
  }
  function send(obj) {
    if (ws && ws.readyState === WebSocket.OPEN) { ws.send(JSON.stringify(obj)); return true; }
    return false;
  }
  function onMessage(m) {
    if ("modes" in m) {
      for (const b of document.querySelectorAll("#modes button")) b.hidden = !m.modes.includes(b.dataset.mode);
    }
    if ("driveMode" in m) { st.mode = m.driveMode; showMode(); }
    if ("recording" in m) { st.recording = !!m.recording; showRecording(); }
    if ("num_records" in m) $("count").textContent = m.num_records;
    if ("control" in m) setRole(m.control);
    if ("health" in m) showHealth(m.health);
    if ("error" in m) showError(m.error);
  }

  // ------------------------------------------------------------------ inputs
  let padStopHeld = false; // B / circle was down at the last look
  function gamepad() {
    const pads = navigator.getGamepads ? navigator.getGamepads() : [];
    const dz = (v) => (Math.abs(v || 0) < 0.12 ? 0 : v);
    let sticks = null, held = false;
    for (const g of pads) {
      if (!g || !g.axes.length) continue;
      if (g.buttons[1] && g.buttons[1].pressed) held = true; // B / circle: stop
      const a = dz(g.axes[0]);
      const t = -dz(g.axes.length > 3 ? g.axes[3] : g.axes[1]); // right stick (Donkeycar's joystick layout)
      if (!sticks && (a || t)) sticks = { a, t };
    }
    // Stop once per press; while B is held, and then until every input is back at rest (as after STOP or
    // space), the sticks do not drive: a stick still forward when B comes up does not start the car again.
    if (held) { if (!padStopHeld) stop(); st.stopLatch = true; }
    padStopHeld = held;
    return sticks;
  }

  function command() {
    let a = 0, t = 0, src = "";
    const gp = gamepad();
    const steerTarget = (keys.has("right") ? 1 : 0) - (keys.has("left") ? 1 : 0);
    keySteer.a += Math.max(-KEY_STEP, Math.min(KEY_STEP, steerTarget - keySteer.a));
    if (pad.id !== null) { a = pad.x; t = -pad.y; src = "touch"; }
    else if (gp) { a = gp.a; t = gp.t; src = "gamepad"; }
    else if (keys.size || keySteer.a) {
      a = keySteer.a; t = (keys.has("up") ? 1 : 0) - (keys.has("down") ? 1 : 0); src = "keys";
    }
    else if (tilt.on && tilt.pitch0 !== null) {
      a = clamp(tilt.steer / 30); t = clamp((tilt.pitch0 - tilt.pitch) / 25); src = "tilt";
    }
    t = clamp(t) * st.limit;
    a = clamp(a);
    if (st.stopLatch) {
      if (src === "" || (a === 0 && t === 0)) st.stopLatch = false; // everything back at rest: stop is over
      else t = 0;
    }
    return { a, t, src, active: src !== "" };
  }

  function tick() {
    const c = command();
    $("angle").textContent = signed(c.a);
    $("throttle").textContent = signed(c.t);
    $("source").textContent = st.stopLatch ? "stopped" : (c.src || "–");
    if (document.visibilityState !== "visible") return;
    // the driver sends every tick, even at rest; a watcher only when it touches something (to take control)
    if (st.control === "you" || c.active) send({ angle: c.a, throttle: c.t });
  }

  // touch (and mouse, and pen) joystick
  const padEl = $("pad"), knob = $("knob");
  function movePad(e) {
    const r = padEl.getBoundingClientRect();
    pad.x = clamp(((e.clientX - r.left) / r.width * 2 - 1) * 1.15);
    pad.y = clamp(((e.clientY - r.top) / r.height * 2 - 1) * 1.15);
    knob.style.transform = `translate(${pad.x * r.width / 2.3}px, ${pad.y * r.height / 2.3}px)`;
  }
  padEl.addEventListener("pointerdown", (e) => {
    if (pad.id !== null) return;
    pad.id = e.pointerId;
    padEl.setPointerCapture(e.pointerId);
    movePad(e);
    wake();
    e.preventDefault();
  });
  padEl.addEventListener("pointermove", (e) => { if (e.pointerId === pad.id) movePad(e); });
  const endPad = (e) => {
    if (e.pointerId !== pad.id) return;
    pad.id = null; pad.x = 0; pad.y = 0;
    knob.style.transform = "";
  };
  for (const ev of ["pointerup", "pointercancel", "lostpointercapture"]) padEl.addEventListener(ev, endPad);

  // keyboard
  const KEYS = { ArrowUp: "up", KeyW: "up", ArrowDown: "down", KeyS: "down", ArrowLeft: "left", KeyA: "left",
                 ArrowRight: "right", KeyD: "right" };
  window.addEventListener("keydown", (e) => {
    if (e.target instanceof HTMLInputElement) return;
    if (e.code === "Space") { stop(); e.preventDefault(); return; }
    const k = KEYS[e.code];
    if (k) { keys.add(k); e.preventDefault(); }
  });
  window.addEventListener("keyup", (e) => { const k = KEYS[e.code]; if (k) keys.delete(k); });
  window.addEventListener("blur", () => keys.clear());

  // device tilt (phones ask for permission on iOS, and only on https pages)
  function onOrientation(e) {
    if (e.beta === null || e.gamma === null) return;
    const angle = (screen.orientation && screen.orientation.angle) || 0;
    let steer = e.gamma, pitch = e.beta;
    if (angle === 90) { steer = e.beta; pitch = -e.gamma; }
    else if (angle === 270) { steer = -e.beta; pitch = e.gamma; }
    if (tilt.pitch0 === null) tilt.pitch0 = pitch; // the way the phone is held when tilt starts is "stopped"
    tilt.steer = steer; tilt.pitch = pitch;
  }
  async function setTilt(on) {
    if (on) {
      if (typeof DeviceOrientationEvent === "undefined") { showError("this device has no motion sensors"); return; }
      if (typeof DeviceOrientationEvent.requestPermission === "function") {
        try {
          if (await DeviceOrientationEvent.requestPermission() !== "granted") { showError("motion sensors not allowed"); return; }
        } catch (err) { showError("motion sensors need an https page: " + err.name); return; }
      }
      tilt.pitch0 = null;
      window.addEventListener("deviceorientation", onOrientation);
    } else {
      window.removeEventListener("deviceorientation", onOrientation);
    }
    tilt.on = on;
    $("tilt").setAttribute("aria-pressed", String(on));
  }
  $("tilt").addEventListener("click", () => setTilt(!tilt.on));

  // ------------------------------------------------------------------ buttons
  function stop() {
    st.stopLatch = true;
    if (tilt.on) setTilt(false);
    send({ stop: true });
  }
  $("stop").addEventListener("click", stop);
  $("stop").addEventListener("pointerdown", (e) => { stop(); e.preventDefault(); }); // no wait for the click
  for (const b of document.querySelectorAll("#modes button")) {
    b.addEventListener("click", () => send({ drive_mode: b.dataset.mode }));
  }
  $("record").addEventListener("click", () => send({ recording: !st.recording }));
  $("release").addEventListener("click", () => send({ release: true }));
  const limit = $("limit");
  limit.value = localStorage.getItem("asyncdonkey.limit") || limit.value;
  const showLimit = () => {
    st.limit = parseFloat(limit.value);
    $("limitv").textContent = st.limit.toFixed(2);
    localStorage.setItem("asyncdonkey.limit", limit.value);
  };
  limit.addEventListener("input", showLimit);
  showLimit();

  // ------------------------------------------------------------------ display
  function setConn(state) { const el = $("conn"); el.dataset.state = state; el.textContent = state; }
  function setRole(role) {
    st.control = role;
    const el = $("control");
    el.dataset.role = role;
    el.textContent = role === "you" ? "you drive" : role === "other" ? "someone else drives" : "free: touch to drive";
    $("release").hidden = role !== "you";
  }
  function showMode() {
    for (const b of document.querySelectorAll("#modes button")) b.setAttribute("aria-pressed", String(b.dataset.mode === st.mode));
  }
  function showRecording() { $("record").setAttribute("aria-pressed", String(st.recording)); }
  function showError(text) {
    const el = $("error");
    el.textContent = text;
    el.hidden = false;
    clearTimeout(errorTimer);
    errorTimer = setTimeout(() => { el.hidden = true; }, 4000);
  }
  function showHealth(h) {
    const out = $("health");
    out.textContent = "";
    const item = (label, value, unit, bad) => {
      if (out.childNodes.length) out.append(" · ");
      const b = document.createElement("b");
      b.textContent = value;
      if (bad) b.className = "bad";
      out.append(label ? label + " " : "", b, unit ? " " + unit : "");
    };
    item("", fmt(h.hz, 1), "Hz");
    if (h.lateness) item("late p99", fmt(h.lateness.p99_ms, 2), "ms", h.lateness.p99_ms > 5);
    for (const [name, l] of Object.entries(h.latency || {})) item(name + " cmd→PWM p50/p99", fmt(l.p50_ms, 1) + "/" + fmt(l.p99_ms, 1), "ms");
    const slow = Object.entries(h.parts || {}).sort((x, y) => y[1].p99_ms - x[1].p99_ms).slice(0, 3);
    for (const [name, p] of slow) item(name, fmt(p.p99_ms, 2), "ms");
    if (typeof h.viewers === "number") item("", String(h.viewers), "watching");
  }

  // ------------------------------------------------------------------ screen wake lock
  function setWake(state, text) { const el = $("wake"); el.dataset.state = state; el.textContent = text; }
  async function wake() {
    if (!("wakeLock" in navigator)) {
      setWake("unavailable", isSecureContext ? "screen may sleep" : "screen may sleep (needs https)");
      return;
    }
    if (wakeLock || document.visibilityState !== "visible") return;
    try {
      wakeLock = await navigator.wakeLock.request("screen");
      setWake("on", "screen stays on");
      wakeLock.addEventListener("release", () => { wakeLock = null; setWake("off", "screen –"); });
    } catch (err) {
      setWake("refused", "screen may sleep (" + err.name + ")");
    }
  }

  // leaving the page hands the car back: the server releases control, and the command ages into the failsafe
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "visible") wake();
    else { keys.clear(); if (st.control === "you") send({ release: true }); }
  });
  window.addEventListener("pagehide", () => { if (st.control === "you") send({ release: true }); });

  connect();
  wake();
  setInterval(tick, SEND_MS);
})();

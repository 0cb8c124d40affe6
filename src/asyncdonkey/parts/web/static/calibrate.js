// Live PWM calibration over /wsCalibrate (Donkeycar's protocol): {"config": {...}}, {"angle"}, {"throttle"}.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  let ws = null;
  const test = { angle: 0, throttle: 0 };

  function connect() {
    ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/wsCalibrate");
    ws.onopen = () => { $("conn").dataset.state = "connected"; $("conn").textContent = "connected"; };
    ws.onclose = () => {
      $("conn").dataset.state = "disconnected"; $("conn").textContent = "disconnected";
      setTimeout(connect, 1000);
    };
    ws.onmessage = (ev) => {
      const m = JSON.parse(ev.data);
      if (m.config) {
        const none = Object.keys(m.config).length === 0;
        $("apply").hidden = none;
        if (none) say("this car gave its web controller no PWM steering or throttle to calibrate", true);
        else { showConfig(m.config); say("in force", false); }
      }
      if (m.error) say(m.error, true);
    };
  }
  function send(obj) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj)); }
  function say(text, bad) { const el = $("msg"); el.textContent = text; el.className = bad ? "bad" : ""; }

  function showConfig(cfg) {
    const form = $("form");
    for (const [name, value] of Object.entries(cfg)) {
      let input = form.querySelector(`input[name="${name}"]`);
      if (!input) {
        const label = document.createElement("label");
        label.textContent = name;
        label.htmlFor = "cfg-" + name;
        input = document.createElement("input");
        input.type = "number"; input.min = "0"; input.max = "4095"; input.step = "1";
        input.name = name; input.id = "cfg-" + name;
        form.append(label, input);
      }
      input.value = value;
    }
  }
  $("apply").addEventListener("click", () => {
    const config = {};
    for (const input of $("form").querySelectorAll("input")) config[input.name] = parseInt(input.value, 10);
    send({ config });
  });
  for (const name of ["angle", "throttle"]) {
    $(name).addEventListener("input", (e) => {
      test[name] = parseFloat(e.target.value);
      $(name + "v").textContent = test[name].toFixed(2);
    });
  }
  $("zero").addEventListener("click", () => {
    for (const name of ["angle", "throttle"]) { test[name] = 0; $(name).value = "0"; $(name + "v").textContent = "0.00"; }
    send({ angle: 0, throttle: 0 });
  });
  // a held test throttle is re-sent steadily: the throttle's failsafe stops a command that stops coming
  setInterval(() => { if (test.angle || test.throttle) send({ angle: test.angle, throttle: test.throttle }); }, 100);
  connect();
})();

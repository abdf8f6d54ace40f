// The console's page: draws the frames the server pushes (GET /api/stream) on a canvas, and
// sends the operator's jammer commands (POST /api/jammer). Every number comes from the server;
// the page keeps only what it draws: each UAV's trail this episode and the two coverage maps.
"use strict";

(() => {
  const token = new URLSearchParams(location.search).get("token");
  const canvas = document.getElementById("map");
  const ctx = canvas.getContext("2d");
  const $ = (id) => document.getElementById(id);
  const STATUS = ["active", "success", "disconnection", "collision", "timeout"];
  const COLOURS = Object.fromEntries(STATUS.map((name) => [
    name, getComputedStyle(document.documentElement).getPropertyValue(`--${name}`).trim()]));
  const UNCOVERED = [38, 42, 60];
  const COVERED_LOW = [251, 231, 161];
  const COVERED_HIGH = [224, 158, 0];
  const TIMELINE_SHOWN = 100;

  const model = {
    scenario: null, frame: null, episode: null, trails: [],
    maps: {}, loaded: {}, showing: "served", timeline: new Map(), background: null,
    drawing: false, drag: null,  // drag: a jammer under the pointer, or a click on the map
  };
  // Read by the tests and the benchmark: frames received (the last at lastAt, ms) and maps.
  window.consoleStats = { frames: 0, lastAt: 0, maps: 0 };

  function withToken(path) {
    if (!token) return path;
    return `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}`;
  }

  async function getJSON(path) {
    const response = await fetch(withToken(path));
    const body = await response.json();
    if (!response.ok) throw new Error(body.error || response.statusText);
    return body;
  }

  // -- coordinates: metres (y up) <-> canvas pixels (y down) -------------------------------
  function toCanvas(x, y) {
    const a = model.scenario.area;
    return [(x - a.x_min) / (a.x_max - a.x_min) * canvas.width,
            (a.y_max - y) / (a.y_max - a.y_min) * canvas.height];
  }

  function toWorld(px, py) {
    const a = model.scenario.area;
    return [a.x_min + px / canvas.width * (a.x_max - a.x_min),
            a.y_max - py / canvas.height * (a.y_max - a.y_min)];
  }

  function metres(length) {
    const a = model.scenario.area;
    return length / (a.x_max - a.x_min) * canvas.width;
  }

  // -- coverage maps -----------------------------------------------------------------------
  function palette(levels) {
    const colours = [UNCOVERED];
    for (let level = 1; level < levels; level++) {
      const f = levels > 2 ? (level - 1) / (levels - 2) : 1;
      colours.push(COVERED_LOW.map((low, i) => Math.round(low + f * (COVERED_HIGH[i] - low))));
    }
    return colours;
  }

  function levelImage(map) {
    const bytes = Uint8Array.from(atob(map.levels), (c) => c.charCodeAt(0));
    const colours = palette(model.scenario.levels);
    const image = new ImageData(map.cols, map.rows);
    for (let row = 0; row < map.rows; row++) {
      const top = map.rows - 1 - row;  // row 0 is the lowest y: the image's last line
      for (let col = 0; col < map.cols; col++) {
        const colour = colours[bytes[row * map.cols + col]] || UNCOVERED;
        const at = 4 * (top * map.cols + col);
        image.data.set([...colour, 255], at);
      }
    }
    const tile = document.createElement("canvas");
    tile.width = map.cols;
    tile.height = map.rows;
    tile.getContext("2d").putImageData(image, 0, 0);
    return tile;
  }

  async function loadMap(which, serial) {
    model.loaded[which] = serial;
    const map = await getJSON(`/api/map/${which}`);
    model.maps[which] = { map, tile: levelImage(map) };
    window.consoleStats.maps++;
    model.background = null;
    schedule();
  }

  // -- drawing: the map and the stations once per map, the moving parts on it per frame -------
  function background() {
    const layer = document.createElement("canvas");
    layer.width = canvas.width;
    layer.height = canvas.height;
    const c = layer.getContext("2d");
    c.fillStyle = `rgb(${UNCOVERED})`;
    c.fillRect(0, 0, layer.width, layer.height);
    const shown = model.maps[model.showing];
    if (shown) {
      const m = shown.map;
      const [left, top] = toCanvas(m.x0 - m.spacing / 2, m.y0 + (m.rows - 0.5) * m.spacing);
      c.imageSmoothingEnabled = false;
      c.drawImage(shown.tile, left, top, metres(m.cols * m.spacing), metres(m.rows * m.spacing));
    }
    drawStations(c);
    return layer;
  }

  function drawStations(ctx) {
    ctx.fillStyle = "#ffffff";
    ctx.strokeStyle = "#262a3c";
    for (const [x, y] of model.scenario.gbs) {
      const [px, py] = toCanvas(x, y);
      ctx.beginPath();
      ctx.moveTo(px, py - 7);
      ctx.lineTo(px + 6, py + 5);
      ctx.lineTo(px - 6, py + 5);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
    }
  }

  function drawFleet(frame) {
    const radius = Math.max(4, metres(model.scenario.uav_radius_m));
    ctx.lineWidth = 2;
    for (const uav of frame.uavs) {
      const colour = COLOURS[uav.status];
      const trail = model.trails[uav.id] || [];
      ctx.strokeStyle = colour;
      ctx.globalAlpha = 0.7;
      ctx.beginPath();
      trail.forEach(([x, y], i) => (i ? ctx.lineTo : ctx.moveTo).call(ctx, ...toCanvas(x, y)));
      ctx.stroke();
      if (uav.status === "active" && uav.destination) {
        const [dx, dy] = toCanvas(...uav.destination);
        ctx.setLineDash([4, 4]);
        ctx.beginPath();
        ctx.moveTo(...toCanvas(uav.x, uav.y));
        ctx.lineTo(dx, dy);
        ctx.stroke();
        ctx.setLineDash([]);
        ctx.beginPath();
        ctx.moveTo(dx - 5, dy - 5); ctx.lineTo(dx + 5, dy + 5);
        ctx.moveTo(dx + 5, dy - 5); ctx.lineTo(dx - 5, dy + 5);
        ctx.stroke();
      }
      ctx.globalAlpha = 1;
      const [px, py] = toCanvas(uav.x, uav.y);
      ctx.fillStyle = colour;
      ctx.strokeStyle = "#ffffff";
      ctx.beginPath();
      ctx.arc(px, py, radius, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
      ctx.fillStyle = "#ffffff";
      ctx.font = "11px system-ui, sans-serif";
      ctx.fillText(String(uav.id), px + radius + 2, py - radius);
    }
  }

  // Each jammer the cloud estimated: a dashed ellipse two standard deviations wide, and where
  // the cloud follows one that moves, an arrow to where it will be in ESTIMATE_ARROW_S.
  const ESTIMATE_ARROW_S = 5;

  function estimatedJammers(estimate) {
    return estimate && estimate.present ? [estimate, ...(estimate.others || [])] : [];
  }

  function drawArrowHead(ax, ay, bx, by) {
    const angle = Math.atan2(by - ay, bx - ax);
    ctx.beginPath();
    ctx.moveTo(bx, by);
    ctx.lineTo(bx - 12 * Math.cos(angle - 0.4), by - 12 * Math.sin(angle - 0.4));
    ctx.moveTo(bx, by);
    ctx.lineTo(bx - 12 * Math.cos(angle + 0.4), by - 12 * Math.sin(angle + 0.4));
    ctx.stroke();
  }

  function drawJammers(frame) {
    for (const estimate of estimatedJammers(frame.estimate)) {
      const [px, py] = toCanvas(estimate.x, estimate.y);
      ctx.strokeStyle = "#ff5fa2";
      ctx.lineWidth = 2;
      ctx.setLineDash([6, 4]);
      ctx.beginPath();
      ctx.ellipse(px, py, Math.max(6, metres(2 * estimate.sd_x_m)),
                  Math.max(6, metres(2 * estimate.sd_y_m)), 0, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.setLineDash([]);
      if (estimate.vx_mps !== null && estimate.vx_mps !== undefined) {
        const [qx, qy] = toCanvas(estimate.x + ESTIMATE_ARROW_S * estimate.vx_mps,
                                  estimate.y + ESTIMATE_ARROW_S * estimate.vy_mps);
        ctx.beginPath();
        ctx.moveTo(px, py);
        ctx.lineTo(qx, qy);
        ctx.stroke();
        drawArrowHead(px, py, qx, qy);
      }
    }
    for (const jammer of frame.jammers) drawJammer(jammer);
  }

  // A jammer: its path, if it drives one, with an arrow at its end (the way it goes), then a
  // diamond where it is now (grey while it does not transmit), its id and power beside it.
  function drawJammer(jammer) {
    if (jammer.path) {
      const corners = jammer.path.map(([x, y]) => toCanvas(x, y));
      ctx.strokeStyle = "#ffffffaa";
      ctx.lineWidth = 2;
      ctx.setLineDash([4, 4]);
      ctx.beginPath();
      corners.forEach(([cx, cy], i) => (i ? ctx.lineTo(cx, cy) : ctx.moveTo(cx, cy)));
      ctx.stroke();
      ctx.setLineDash([]);
      const [[ax, ay], [bx, by]] = corners.slice(-2);
      drawArrowHead(ax, ay, bx, by);
    }
    const [px, py] = dragged(jammer);
    ctx.fillStyle = jammer.on ? COLOURS.collision : "#888888";
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(px, py - 10); ctx.lineTo(px + 10, py); ctx.lineTo(px, py + 10);
    ctx.lineTo(px - 10, py);
    ctx.closePath();
    ctx.fill();
    ctx.stroke();
    ctx.fillStyle = "#ffffff";
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillText(`J${jammer.id} ${jammer.power_w} W`, px + 12, py + 4);
  }

  // Where a jammer is drawn: under the pointer while it is dragged.
  function dragged(jammer) {
    const drag = model.drag;
    return drag && drag.id === jammer.id && drag.moved ? [drag.px, drag.py]
      : toCanvas(jammer.x, jammer.y);
  }

  function draw() {
    model.drawing = false;
    if (!model.scenario || !model.frame) return;
    model.background = model.background || background();
    ctx.drawImage(model.background, 0, 0);
    drawFleet(model.frame);
    drawJammers(model.frame);
  }

  // Drawn only when something changed, at the browser's next paint.
  function schedule() {
    if (!model.drawing) {
      model.drawing = true;
      requestAnimationFrame(draw);
    }
  }

  // -- the side panel --------------------------------------------------------------------------
  function describeJammer(jammer) {
    return `J${jammer.id} (${jammer.x.toFixed(1)}, ${jammer.y.toFixed(1)}) m, `
      + `${jammer.power_w} W${jammer.path ? ", driving" : ""}${jammer.on ? "" : ", silent now"}`;
  }

  // One line per jammer in force, each with its remove button (rebuilt when the set changes).
  function renderJammers(frame) {
    const list = $("jammer-list");
    const key = JSON.stringify(frame.jammers.map((j) => [j.id, j.power_w, j.path]));
    if (list.dataset.key !== key) {
      list.dataset.key = key;
      list.replaceChildren(...frame.jammers.map((jammer) => {
        const item = document.createElement("li");
        item.dataset.id = jammer.id;
        const text = document.createElement("span");
        const remove = document.createElement("button");
        remove.type = "button";
        remove.textContent = "Remove";
        remove.addEventListener("click", () => command({ remove: jammer.id }).catch(showRefusal));
        item.append(text, " ", remove);
        return item;
      }));
    }
    for (const jammer of frame.jammers) {
      const item = list.querySelector(`li[data-id="${jammer.id}"] span`);
      if (item && item.textContent !== describeJammer(jammer)) {
        item.textContent = describeJammer(jammer);
      }
    }
  }

  function show(id, text) {
    const element = $(id);
    if (element.textContent !== String(text)) element.textContent = text;
  }

  function renderPanel(frame) {
    const where = frame.episode === null ? "waiting for the world"
      : `episode ${frame.episode}, step ${frame.step} (${frame.clock})`;
    const map = frame.map_version === null ? "no map yet" : `map v${frame.map_version} `
      + `(${frame.map_mode}${frame.map_accuracy === null ? ""
        : `, ${(100 * frame.map_accuracy).toFixed(1)} % held-out`})`;
    show("status", `${where} · ${map}${frame.finished ? " · run finished" : ""}`);
    show("served-version", frame.map_version === null ? "" : `(v${frame.map_version})`);
    show("jammer-text", !frame.jammer_known ? "In force: not known yet"
      : frame.jammers.length ? "In force:" : "In force: none");
    renderJammers(frame);
    show("estimate-text", estimateText(frame));
    for (const [name, count] of Object.entries(frame.counters)) show(`n-${name}`, count);
  }

  // While a provisional map is in service the cloud has counted jammers it cannot place yet:
  // that count, not an older estimate, is what it knows now.
  function estimateText(frame) {
    const counted = frame.jammers_counted;
    if (frame.map_provisional && counted !== null && counted !== undefined) {
      return `Cloud's count: ${counted} jammer${counted === 1 ? "" : "s"}, not placed yet `
        + "(provisional map)";
    }
    const e = frame.estimate;
    return !e ? "" : e.present
      ? `Cloud's estimate (map v${e.map_version}): ` + estimatedJammers(e).map((j) =>
        `${j.id}: (${j.x.toFixed(1)} ± ${j.sd_x_m.toFixed(1)}, `
        + `${j.y.toFixed(1)} ± ${j.sd_y_m.toFixed(1)}) m, ${j.power_w.toFixed(2)} W`
        + (j.vx_mps === null || j.vx_mps === undefined ? ""
          : `, moving (${j.vx_mps.toFixed(1)}, ${j.vy_mps.toFixed(1)}) m/s`)).join("; ")
      : `Cloud's estimate (map v${e.map_version}): no jammer`;
  }

  function renderTimeline(entries) {
    const fresh = entries.filter((entry) => !model.timeline.has(entry.seq));
    if (!fresh.length) return;
    fresh.forEach((entry) => model.timeline.set(entry.seq, entry));
    const newest = [...model.timeline.values()].sort((a, b) => b.seq - a.seq)
      .slice(0, TIMELINE_SHOWN);
    model.timeline = new Map(newest.map((entry) => [entry.seq, entry]));
    $("timeline").replaceChildren(...newest.map((entry) => {
      const item = document.createElement("li");
      item.dataset.kind = entry.kind;
      const time = document.createElement("time");
      time.textContent = new Date(entry.t * 1000).toLocaleTimeString();
      item.append(time, entry.text);
      return item;
    }));
  }

  // -- frames ------------------------------------------------------------------------------------
  function onFrame(frame) {
    window.consoleStats.frames++;
    window.consoleStats.lastAt = performance.now();
    if (frame.episode !== model.episode) {
      model.episode = frame.episode;
      model.trails = frame.trails || [];
    }
    for (const uav of frame.uavs) {
      const trail = model.trails[uav.id] || (model.trails[uav.id] = []);
      const last = trail[trail.length - 1];
      if (!last || last[0] !== uav.x || last[1] !== uav.y) trail.push([uav.x, uav.y]);
    }
    for (const [which, serial] of Object.entries(frame.maps)) {
      if (model.loaded[which] !== serial) loadMap(which, serial).catch(showRefusal);
    }
    model.frame = frame;
    schedule();
    renderPanel(frame);
    renderTimeline(frame.timeline);
  }

  // -- the operator's hand -----------------------------------------------------------------------
  function showRefusal(error) {
    $("message").textContent = String(error.message || error);
    $("message").className = "refused";
  }

  async function command(body) {
    const response = await fetch(withToken("/api/jammer"), {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify(body),
    });
    const reply = await response.json();
    if (!response.ok) throw new Error(`refused: ${reply.error}`);
    $("message").textContent = `${reply.jammers.length} jammer(s) in force from the next step`;
    $("message").className = "";
  }

  // The pointer on the map: pressed on a jammer, a drag moves it there; pressed anywhere else,
  // a click adds a jammer of the power set beside.
  function pointer(event) {
    const box = canvas.getBoundingClientRect();
    return [(event.clientX - box.left) * canvas.width / box.width,
            (event.clientY - box.top) * canvas.height / box.height];
  }
  const round = (v) => Math.round(v * 10) / 10;

  canvas.addEventListener("pointerdown", (event) => {
    if (!model.scenario || !model.frame) return;
    const [px, py] = pointer(event);
    const hit = model.frame.jammers.find((jammer) => {
      const [jx, jy] = toCanvas(jammer.x, jammer.y);
      return Math.hypot(jx - px, jy - py) <= 12;
    });
    model.drag = { id: hit ? hit.id : null, startX: px, startY: py, px, py, moved: false };
    canvas.setPointerCapture(event.pointerId);
  });
  canvas.addEventListener("pointermove", (event) => {
    const drag = model.drag;
    if (!drag || drag.id === null) return;
    [drag.px, drag.py] = pointer(event);
    drag.moved = drag.moved || Math.hypot(drag.px - drag.startX, drag.py - drag.startY) > 3;
    schedule();
  });
  canvas.addEventListener("pointerup", (event) => {
    const drag = model.drag;
    model.drag = null;
    if (!drag) return;
    const [x, y] = toWorld(...pointer(event));
    if (drag.id !== null) {
      if (drag.moved) {
        command({ id: drag.id, x: round(x), y: round(y) }).catch(showRefusal);
      }
      schedule();
      return;
    }
    command({ x: round(x), y: round(y), power_w: Number($("power").value), add: true })
      .catch(showRefusal);
  });
  $("off").addEventListener("click", () => command({ off: true }).catch(showRefusal));
  for (const choice of document.querySelectorAll("input[name=coverage]")) {
    choice.addEventListener("change", () => {
      model.showing = choice.value;
      model.background = null;
      schedule();
    });
  }

  async function start() {
    try {
      model.scenario = await getJSON("/api/scenario");
      $("power").value = model.scenario.jammer_power_w || 1;
      onFrame(await getJSON("/api/state"));
    } catch (error) {
      $("status").textContent = String(error.message || error);
      return;
    }
    const stream = new EventSource(withToken("/api/stream"));
    stream.onmessage = (event) => onFrame(JSON.parse(event.data));
    stream.onerror = () => show("status", "connection lost, reconnecting…");
  }

  start();
})();

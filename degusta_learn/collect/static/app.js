/* degusta collect: the participant page (docs/collect_api.md is the contract with the server).
 *
 * Plain JavaScript, no framework, no external resources. Every string from the server or the dataset is put
 * into the page as text (textContent, attribute values), never as HTML. */
"use strict";

(function () {
  const SVGNS = "http://www.w3.org/2000/svg";
  const DRAFT_DELAY_MS = 300;
  const NUDGE = 0.005;        // arrow key step (normalized table units); Shift: 4x
  const DRAG_THRESHOLD = 4;   // CSS pixels before a press on the palette becomes a drag
  const RATING_STAGES = ["rate_initial", "rate_jitter", "rate_correct"];
  const EDIT_STAGES = ["arrange", "correct"];

  const $ = (id) => document.getElementById(id);
  const el = {};
  [
    "title", "progress", "alert", "alert-text", "alert-close", "screen-loading", "screen-start", "screen-task",
    "screen-done", "start-heading", "instructions", "start-form", "pid-row", "pid", "start-button",
    "stage-heading", "stage-help", "table-wrap", "table-svg", "table-image", "surface-outline", "objects-layer",
    "palette", "types", "objects", "objects-title", "place-centre", "selection", "selection-label",
    "rotate-left", "rotate-right", "rotation-number", "rotation-slider", "remove", "rating-panel", "rating",
    "rating-value", "count", "validity", "undo", "submit", "save-status", "drag-ghost", "done-heading",
  ].forEach((id) => { el[id] = $(id); });

  /* ---------------------------------------------------------------- state */

  const app = {
    study: null,          // GET /api/study
    objects: new Map(),   // id -> catalog object
    state: null,          // the last state from the server
    table: null,          // the current table (from study.tables)
    placements: [],       // what is drawn: [{object, x, y, rotation}] in placement order
    selected: null,       // object id of the selected placement
    armed: null,          // object id chosen in the palette, to be placed
    activeType: null,     // the palette's open type
    history: [],          // undo stack of placement lists
    historyKey: null,     // coalesces repeated small edits (nudges, slider) into one undo step
    historyTime: 0,
    ratingMoved: false,
    busy: false,          // a submit is in flight
    draftTimer: null,
    draftInFlight: false,
    draftAgain: false,
    drag: null,           // the pointer gesture on the table
    paletteDrag: null,    // a press on a palette object that may become a drag
    suppressClick: false,
    nodes: new Map(),     // object id -> its <g> on the table
    screenScale: 1,       // CSS pixels per table-image pixel
    ready: false,
  };

  /* ---------------------------------------------------------------- helpers */

  function clamp(v, lo, hi) { return Math.min(hi, Math.max(lo, v)); }

  function normRotation(r) {
    let v = Number(r) % 360;
    if (v < 0) v += 360;
    if (v >= 360 || !Number.isFinite(v)) v = 0;
    return v;
  }

  function copyPlacements(list) {
    return list.map((p) => ({ object: p.object, x: p.x, y: p.y, rotation: p.rotation }));
  }

  function samePlacements(a, b) {
    if (a.length !== b.length) return false;
    for (let i = 0; i < a.length; i++) {
      const p = a[i], q = b[i];
      if (p.object !== q.object || p.x !== q.x || p.y !== q.y || p.rotation !== q.rotation) return false;
    }
    return true;
  }

  /** A random submission id: crypto.randomUUID where the page is a secure context, else getRandomValues. */
  function freshId() {
    const c = window.crypto;
    if (c && typeof c.randomUUID === "function") {
      try { return c.randomUUID(); } catch (e) { /* not a secure context: fall through */ }
    }
    const bytes = new Uint8Array(16);
    if (c && typeof c.getRandomValues === "function") {
      c.getRandomValues(bytes);
    } else {
      for (let i = 0; i < 16; i++) bytes[i] = Math.floor(Math.random() * 256);
    }
    bytes[6] = (bytes[6] & 0x0f) | 0x40;
    bytes[8] = (bytes[8] & 0x3f) | 0x80;
    const hex = Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
    return `${hex.slice(0, 8)}-${hex.slice(8, 12)}-${hex.slice(12, 16)}-${hex.slice(16, 20)}-${hex.slice(20)}`;
  }

  /** Only same-origin paths from the server are used as picture addresses. */
  function safePath(p) {
    return typeof p === "string" && p.startsWith("/") && !p.startsWith("//") ? p : "";
  }

  /** Even-odd point in polygon (the rule of scene.Table.contains). */
  function insidePolygon(x, y, poly) {
    let inside = false;
    for (let i = 0, j = poly.length - 1; i < poly.length; j = i++) {
      const xa = poly[i][0], ya = poly[i][1], xb = poly[j][0], yb = poly[j][1];
      if ((ya > y) !== (yb > y)) {
        const xAt = xa + (y - ya) * (xb - xa) / (yb - ya);
        if (x < xAt) inside = !inside;
      }
    }
    return inside;
  }

  function onSurface(p) {
    return app.table ? insidePolygon(p.x, p.y, app.table.surface) : false;
  }

  function plural(n, one, many) { return n === 1 ? one : many; }

  const PLURALS = { knife: "knives", glass: "glasses", dish: "dishes" };

  function typeName(type, n) {
    const s = String(type);
    const word = n === 1 ? s : (PLURALS[s] || (/(s|x|ch|sh)$/.test(s) ? s + "es" : s + "s"));
    return word.charAt(0).toUpperCase() + word.slice(1);
  }

  function labelOf(id) {
    const o = app.objects.get(id);
    return o ? String(o.label || `${o.type} ${id}`) : `object ${id}`;
  }

  /* ---------------------------------------------------------------- the server */

  class ApiError extends Error {
    constructor(status, detail) { super(detail); this.status = status; this.detail = detail; }
  }

  function detailOf(data, status) {
    if (data && typeof data.detail === "string") return data.detail;
    if (data && Array.isArray(data.detail) && data.detail.length) {
      return data.detail.map((d) => (d && typeof d.msg === "string" ? d.msg : String(d))).join("; ");
    }
    return `The server answered ${status}.`;
  }

  async function api(method, path, body) {
    const opts = { method, headers: { Accept: "application/json" }, credentials: "same-origin", cache: "no-store" };
    if (body !== undefined) {
      opts.headers["Content-Type"] = "application/json";
      opts.body = JSON.stringify(body);
    }
    let resp;
    try {
      resp = await fetch(path, opts);
    } catch (e) {
      throw new ApiError(0, "The study server cannot be reached. Check the connection, then try again.");
    }
    let data = null;
    try { data = await resp.json(); } catch (e) { data = null; }
    if (!resp.ok) throw new ApiError(resp.status, detailOf(data, resp.status));
    return data;
  }

  /* ---------------------------------------------------------------- messages */

  function showError(text) {
    el["alert-text"].textContent = String(text);
    el.alert.hidden = false;
  }

  function clearError() {
    el.alert.hidden = true;
    el["alert-text"].textContent = "";
  }

  el["alert-close"].addEventListener("click", clearError);

  function showScreen(name) {
    for (const s of ["loading", "start", "task", "done"]) el[`screen-${s}`].hidden = s !== name;
  }

  /* ---------------------------------------------------------------- start */

  async function boot() {
    let study;
    try {
      study = await api("GET", "/api/study");
    } catch (e) {
      showScreen("loading");
      showError(e.detail || String(e));
      return;
    }
    setStudy(study);
    await loadState();
  }

  function setStudy(study) {
    app.study = study;
    app.objects = new Map((study.objects || []).map((o) => [o.id, o]));
    const title = String(study.title || "Set the table");
    el.title.textContent = title;
    document.title = title;
    el.instructions.replaceChildren();
    const paragraphs = String(study.instructions || "").split(/\r?\n[ \t]*\r?\n/);
    for (const text of paragraphs) {
      if (!text.trim()) continue;
      const p = document.createElement("p");
      p.textContent = text.trim();
      el.instructions.appendChild(p);
    }
    el["pid-row"].hidden = study.participant_ids !== "enter";
    buildTypes();
  }

  async function loadState() {
    try {
      const state = await api("GET", "/api/state");
      showState(state);
    } catch (e) {
      if (e.status === 401) {
        showStart();
      } else {
        showError(e.detail);
      }
    }
  }

  function showStart() {
    app.state = null;
    document.body.className = "";
    document.body.dataset.stage = "start";
    el.progress.textContent = "";
    showScreen("start");
    el["start-button"].disabled = false;
    if (app.study && app.study.participant_ids === "enter") el.pid.focus();
    else el["start-heading"].focus();
    markReady();
  }

  el["start-form"].addEventListener("submit", async (ev) => {
    ev.preventDefault();
    if (el["start-button"].disabled) return;
    clearError();
    const body = app.study && app.study.participant_ids === "enter" ? { participant: el.pid.value.trim() } : {};
    el["start-button"].disabled = true;
    try {
      const state = await api("POST", "/api/session", body);
      showState(state);
    } catch (e) {
      showError(e.detail);
      el["start-button"].disabled = false;
      if (!el["pid-row"].hidden) el.pid.focus();
    }
  });

  /* ---------------------------------------------------------------- a stage */

  const STAGE_TEXT = {
    arrange: ["Set the table", "Set this table the way you like it. Choose a kind of object, then an object, then click on the table where it goes (or drag it there)."],
    rate_initial: ["Rate your table", "This is the table you set."],
    rate_jitter: ["Rate this table", "This is a changed copy of your table."],
    correct: ["Put the table right", "Move and turn the objects back to how you want them. Objects cannot be added or removed now."],
    rate_correct: ["Rate the corrected table", "This is the table as you put it right."],
  };

  function showState(state) {
    clearTimeout(app.draftTimer);
    app.draftTimer = null;
    const sameStage = app.state && state && app.state.trial === state.trial && app.state.stage === state.stage;
    app.state = state;
    if (state.stage === "done") {
      el.progress.textContent = `${state.trials} of ${state.trials} tables done`;
      document.body.className = "stage-done";
      document.body.dataset.stage = "done";
      document.body.dataset.trial = String(state.trial);
      showScreen("done");
      el["done-heading"].focus();
      markReady();
      return;
    }
    const table = (app.study.tables || []).find((t) => t.id === state.table);
    if (!table) {
      showError(`The study has no table ${state.table}. Please tell the researcher.`);
      return;
    }
    app.table = table;
    const stage = state.stage;
    const editable = EDIT_STAGES.includes(stage);
    const source = editable ? state.draft : state.scene;
    app.placements = Array.isArray(source)
      ? source.map((p) => ({ object: p.object, x: Number(p.x), y: Number(p.y), rotation: normRotation(p.rotation) }))
      : [];
    if (!sameStage) {
      app.history = [];
      app.historyKey = null;
      app.selected = null;
      app.armed = null;
      app.ratingMoved = false;
      el.rating.value = "50";
    }
    if (app.selected !== null && !app.placements.some((p) => p.object === app.selected)) app.selected = null;
    const [heading, help] = STAGE_TEXT[stage] || [stage, ""];
    el["stage-heading"].textContent = heading;
    el["stage-help"].textContent = help;
    el.progress.textContent = `Table ${state.trial + 1} of ${state.trials}`;
    document.body.className = RATING_STAGES.includes(stage) ? "stage-rate" : `stage-${stage}`;
    document.body.dataset.stage = stage;
    document.body.dataset.trial = String(state.trial);
    el["rating-panel"].hidden = !RATING_STAGES.includes(stage);
    el["table-svg"].classList.toggle("readonly", !editable);
    el["table-svg"].setAttribute("aria-label", `The table (${table.name || "table " + table.id})`);
    el.submit.textContent = RATING_STAGES.includes(stage) ? "Submit rating" : "Submit";
    el["save-status"].textContent = "";
    showScreen("task");
    setUpTable();
    if (stage === "arrange") buildObjects();  // a type's objects show once its icon is chosen (the paper)
    updateRating();
    render();
    if (!sameStage) el["stage-heading"].focus();
    markReady();
  }

  /** The first screen is drawn (benchmarks/bench_collect.py reads this mark). */
  function markReady() {
    if (app.ready) return;
    app.ready = true;
    try { performance.mark("degusta:ready"); } catch (e) { /* no User Timing */ }
  }

  function setUpTable() {
    const t = app.table;
    const svg = el["table-svg"];
    svg.setAttribute("viewBox", `0 0 ${t.width} ${t.height}`);
    const img = el["table-image"];
    img.setAttribute("width", t.width);
    img.setAttribute("height", t.height);
    const href = safePath(t.image);
    if (img.getAttribute("href") !== href) img.setAttribute("href", href);
    el["surface-outline"].setAttribute("points",
      t.surface.map(([x, y]) => `${x * t.width},${y * t.height}`).join(" "));
    for (const node of app.nodes.values()) node.remove();
    app.nodes.clear();
    layout();
  }

  /** Fit the table in the left column and the window, keeping its aspect. */
  function layout() {
    if (!app.table || el["screen-task"].hidden) return;
    const t = app.table;
    const wrap = el["table-wrap"];
    const availW = Math.max(200, wrap.clientWidth);
    const top = wrap.getBoundingClientRect().top + window.scrollY;
    const availH = Math.max(320, window.innerHeight - top - 16);
    const s = Math.min(availW / t.width, availH / t.height);
    const w = Math.floor(t.width * s), h = Math.floor(t.height * s);
    el["table-svg"].style.width = `${w}px`;
    el["table-svg"].style.height = `${h}px`;
    app.screenScale = w / t.width;
    if (app.nodes.size) render();
  }

  window.addEventListener("resize", () => layout());

  /* ---------------------------------------------------------------- the palette */

  function buildTypes() {
    el.types.replaceChildren();
    for (const t of app.study.types || []) {
      const b = document.createElement("button");
      b.type = "button";
      b.className = "type-button";
      b.dataset.type = String(t.type);
      b.setAttribute("aria-pressed", "false");
      b.setAttribute("aria-label", `${typeName(t.type, 2)} (${t.count})`);
      const img = document.createElement("img");
      img.alt = "";
      img.src = safePath(t.icon);
      img.draggable = false;
      const span = document.createElement("span");
      span.textContent = typeName(t.type, 2);
      b.append(img, span);
      b.addEventListener("click", () => {
        app.activeType = String(t.type);
        buildObjects();
        const first = el.objects.querySelector("button:not(:disabled)");
        if (first) first.focus();
      });
      el.types.appendChild(b);
    }
  }

  function buildObjects() {
    for (const b of el.types.children) b.setAttribute("aria-pressed", String(b.dataset.type === app.activeType));
    el.objects.replaceChildren();
    const objs = (app.study.objects || []).filter((o) => o.type === app.activeType);
    el["objects-title"].textContent = app.activeType === null ? "Choose an object"
      : `Choose a ${String(app.activeType)} (${objs.length})`;
    for (const o of objs) {
      const b = document.createElement("button");
      b.type = "button";
      b.className = "object-button";
      b.dataset.object = String(o.id);
      b.title = String(o.label || "");
      const img = document.createElement("img");
      img.alt = "";
      img.src = safePath(o.image);
      img.draggable = false;
      b.appendChild(img);
      b.addEventListener("click", (ev) => {
        if (app.suppressClick) { app.suppressClick = false; ev.preventDefault(); return; }
        if (isUsed(o.id)) return;
        app.armed = app.armed === o.id ? null : o.id;
        updatePalette();
        updateControls();
      });
      b.addEventListener("pointerdown", (ev) => startPaletteDrag(ev, o.id));
      el.objects.appendChild(b);
    }
    updatePalette();
  }

  function isUsed(id) { return app.placements.some((p) => p.object === id); }

  function updatePalette() {
    for (const b of el.objects.children) {
      const id = Number(b.dataset.object);
      const used = isUsed(id);
      const label = labelOf(id);
      b.classList.toggle("used", used);
      b.disabled = used;
      b.setAttribute("aria-pressed", String(app.armed === id));
      b.setAttribute("aria-label", used ? `${label} (on the table)` : label);
    }
    el["table-svg"].classList.toggle("placing", app.armed !== null);
    el["place-centre"].disabled = !(app.armed !== null && app.state && app.state.stage === "arrange");
  }

  /* ---------------------------------------------------------------- drawing */

  function svgNode(name, attrs) {
    const n = document.createElementNS(SVGNS, name);
    for (const [k, v] of Object.entries(attrs || {})) n.setAttribute(k, String(v));
    return n;
  }

  function sizeOf(id) {
    const t = app.table, o = app.objects.get(id);
    const unit = Math.sqrt(t.width * t.height);
    const w = o ? Number(o.width) : 0.08, l = o ? Number(o.length) : 0.08;
    return [w * unit, l * unit];
  }

  function makeNode(id) {
    const o = app.objects.get(id);
    const g = svgNode("g", { class: "placed", "data-object": id });
    const hit = svgNode("rect", { class: "hit" });
    const image = svgNode("image", { preserveAspectRatio: "xMidYMid meet" });
    image.setAttribute("href", safePath(o ? o.image : ""));
    const frame = svgNode("rect", { class: "frame", "vector-effect": "non-scaling-stroke", rx: 3 });
    const line = svgNode("line", { class: "handle-line", "vector-effect": "non-scaling-stroke" });
    const handle = svgNode("circle", { class: "handle", "data-handle": "rotate", "vector-effect": "non-scaling-stroke" });
    const title = svgNode("title");
    title.textContent = labelOf(id);
    g.append(title, hit, image, frame, line, handle);
    g.addEventListener("focus", () => {
      if (EDIT_STAGES.includes(app.state.stage) && app.selected !== id) { app.selected = id; render(); }
    });
    return g;
  }

  function render() {
    if (!app.table || !app.state) return;
    const editable = EDIT_STAGES.includes(app.state.stage);
    const layer = el["objects-layer"];
    const keep = new Set(app.placements.map((p) => p.object));
    for (const [id, node] of app.nodes) {
      if (!keep.has(id)) { node.remove(); app.nodes.delete(id); }
    }
    const px = 1 / (app.screenScale || 1);  // one CSS pixel in table-image pixels
    app.placements.forEach((p, i) => {
      let g = app.nodes.get(p.object);
      if (!g) { g = makeNode(p.object); app.nodes.set(p.object, g); }
      if (layer.children[i] !== g) layer.insertBefore(g, layer.children[i] || null);
      const [w, l] = sizeOf(p.object);
      const cx = p.x * app.table.width, cy = p.y * app.table.height;
      g.setAttribute("transform", `translate(${cx} ${cy}) rotate(${p.rotation})`);
      const image = g.querySelector("image");
      image.setAttribute("x", -w / 2); image.setAttribute("y", -l / 2);
      image.setAttribute("width", w); image.setAttribute("height", l);
      const hw = Math.max(w, 22 * px), hl = Math.max(l, 22 * px);  // thin cutlery stays easy to grab
      const hit = g.querySelector(".hit");
      hit.setAttribute("x", -hw / 2); hit.setAttribute("y", -hl / 2);
      hit.setAttribute("width", hw); hit.setAttribute("height", hl);
      const pad = 4 * px;
      const frame = g.querySelector(".frame");
      frame.setAttribute("x", -w / 2 - pad); frame.setAttribute("y", -l / 2 - pad);
      frame.setAttribute("width", w + 2 * pad); frame.setAttribute("height", l + 2 * pad);
      const hy = -l / 2 - pad - 18 * px;
      const line = g.querySelector(".handle-line");
      line.setAttribute("x1", 0); line.setAttribute("y1", -l / 2 - pad);
      line.setAttribute("x2", 0); line.setAttribute("y2", hy);
      const handle = g.querySelector(".handle");
      handle.setAttribute("cx", 0); handle.setAttribute("cy", hy); handle.setAttribute("r", 7 * px);
      const selected = editable && app.selected === p.object;
      const off = editable && !onSurface(p);
      g.classList.toggle("selected", selected);
      g.classList.toggle("off", off);
      g.setAttribute("data-x", p.x.toFixed(4));
      g.setAttribute("data-y", p.y.toFixed(4));
      g.setAttribute("data-rotation", p.rotation.toFixed(1));
      if (editable) {
        g.setAttribute("tabindex", "0");
        g.setAttribute("role", "button");
        g.setAttribute("aria-pressed", String(selected));
        g.setAttribute("aria-label", `${labelOf(p.object)}, ${Math.round(p.x * 100)}% across, ` +
          `${Math.round(p.y * 100)}% down, turned ${Math.round(p.rotation)}°${off ? ", off the table" : ""}`);
      } else {
        g.removeAttribute("tabindex");
        g.setAttribute("role", "img");
        g.removeAttribute("aria-pressed");
        g.setAttribute("aria-label", labelOf(p.object));
      }
    });
    const anyOff = editable && app.placements.some((p) => !onSurface(p));
    el["surface-outline"].classList.toggle("show", anyOff || (app.drag !== null && app.drag.moved)
      || app.paletteDrag !== null && app.paletteDrag.dragging);
    if (app.state.stage === "arrange") updatePalette();
    updateControls();
  }

  function updateControls() {
    const stage = app.state ? app.state.stage : null;
    const editable = EDIT_STAGES.includes(stage);
    const sel = app.placements.find((p) => p.object === app.selected);
    const hasSel = editable && !!sel;
    el["rotate-left"].disabled = !hasSel;
    el["rotate-right"].disabled = !hasSel;
    el["rotation-number"].disabled = !hasSel;
    el["rotation-slider"].disabled = !hasSel;
    el.remove.disabled = !(hasSel && stage === "arrange");
    if (hasSel) {
      el["selection-label"].textContent = labelOf(sel.object);
      el["selection-label"].classList.add("active");
      const r = String(Math.round(sel.rotation) % 360);
      if (document.activeElement !== el["rotation-number"]) el["rotation-number"].value = r;
      el["rotation-slider"].value = r;
    } else {
      el["selection-label"].textContent = "nothing (click an object on the table)";
      el["selection-label"].classList.remove("active");
      el["rotation-number"].value = "";
      el["rotation-slider"].value = "0";
    }
    el.undo.disabled = !editable || app.history.length === 0 || app.busy;
    const n = app.placements.length;
    const min = app.state ? app.state.min_objects : 0;
    el.count.textContent = `${n} ${plural(n, "object", "objects")} placed (at least ${min})`;
    el.count.classList.toggle("short", editable && n < min);
    let problem = "";
    if (editable) {
      const off = app.placements.filter((p) => !onSurface(p)).length;
      if (off) problem = `${off} ${plural(off, "object is", "objects are")} off the table: move ${plural(off, "it", "them")} onto the table.`;
      else if (n < min) problem = `Place ${min - n} more ${plural(min - n, "object", "objects")} to submit.`;
    }
    el.validity.textContent = problem;
    el.validity.classList.toggle("ok", !problem);
    el.submit.disabled = app.busy || !canSubmit();
  }

  function canSubmit() {
    if (!app.state) return false;
    const stage = app.state.stage;
    if (EDIT_STAGES.includes(stage)) {
      return app.placements.length >= app.state.min_objects && app.placements.every(onSurface);
    }
    if (RATING_STAGES.includes(stage)) return app.ratingMoved;
    return false;
  }

  /* ---------------------------------------------------------------- editing */

  /** Record the list before a change, for undo; edits with the same key close together are one step. */
  function remember(key) {
    const now = Date.now();
    if (key && key === app.historyKey && now - app.historyTime < 1000) { app.historyTime = now; return; }
    app.history.push(copyPlacements(app.placements));
    if (app.history.length > 200) app.history.shift();
    app.historyKey = key || null;
    app.historyTime = now;
  }

  function changed() {
    render();
    scheduleDraft();
  }

  function placeNew(id, x, y) {
    if (app.state.stage !== "arrange" || isUsed(id) || !app.objects.has(id)) return false;
    remember(null);
    app.placements.push({ object: id, x: clamp(x, 0, 1), y: clamp(y, 0, 1), rotation: 0 });
    app.selected = id;
    app.armed = null;
    changed();
    return true;
  }

  function moveTo(id, x, y) {
    const p = app.placements.find((q) => q.object === id);
    if (!p) return;
    p.x = clamp(x, 0, 1);
    p.y = clamp(y, 0, 1);
  }

  function rotateSelected(delta, key) {
    const p = app.placements.find((q) => q.object === app.selected);
    if (!p) return;
    remember(key || null);
    p.rotation = normRotation(Math.round(p.rotation) + delta);
    changed();
  }

  function setRotation(value, key) {
    const p = app.placements.find((q) => q.object === app.selected);
    const v = Number(value);
    if (!p || !Number.isFinite(v)) return;
    const r = normRotation(Math.round(v));
    if (r === p.rotation) return;
    remember(key);
    p.rotation = r;
    changed();
  }

  function removeSelected() {
    if (app.state.stage !== "arrange" || app.selected === null) return;
    const i = app.placements.findIndex((q) => q.object === app.selected);
    if (i < 0) return;
    remember(null);
    app.placements.splice(i, 1);
    app.selected = null;
    changed();
    el["table-svg"].focus();
  }

  function undo() {
    if (!EDIT_STAGES.includes(app.state && app.state.stage) || !app.history.length || app.busy) return;
    app.placements = app.history.pop();
    app.historyKey = null;
    if (app.selected !== null && !isUsed(app.selected)) app.selected = null;
    changed();
  }

  function nudge(dx, dy) {
    const p = app.placements.find((q) => q.object === app.selected);
    if (!p) return;
    remember(`nudge:${p.object}`);
    moveTo(p.object, p.x + dx, p.y + dy);
    changed();
  }

  function surfaceCentre() {
    const s = app.table.surface;
    const xs = s.map((q) => q[0]), ys = s.map((q) => q[1]);
    let x = (Math.min(...xs) + Math.max(...xs)) / 2, y = (Math.min(...ys) + Math.max(...ys)) / 2;
    if (!insidePolygon(x, y, s)) {  // a concave surface: the mean of its corners, else its first corner nudged in
      x = xs.reduce((a, b) => a + b, 0) / xs.length;
      y = ys.reduce((a, b) => a + b, 0) / ys.length;
    }
    return [x, y];
  }

  function placeArmedInMiddle() {
    if (app.armed === null) return;
    const [x, y] = surfaceCentre();
    const id = app.armed;
    if (placeNew(id, x, y)) focusPlaced(id);
  }

  function focusPlaced(id) {
    const g = app.nodes.get(id);
    if (g) g.focus({ preventScroll: true });
  }

  el["rotate-left"].addEventListener("click", () => rotateSelected(-15));
  el["rotate-right"].addEventListener("click", () => rotateSelected(15));
  el["rotation-number"].addEventListener("change", () => {
    setRotation(el["rotation-number"].value, `rotnum:${app.selected}`);
    const p = app.placements.find((q) => q.object === app.selected);
    if (p) el["rotation-number"].value = String(Math.round(p.rotation) % 360);  // 400 reads back as 40
  });
  el["rotation-number"].addEventListener("input", () => {
    if (el["rotation-number"].value !== "") setRotation(el["rotation-number"].value, `rotnum:${app.selected}`);
  });
  el["rotation-slider"].addEventListener("input", () => setRotation(el["rotation-slider"].value, `rotslider:${app.selected}`));
  el.remove.addEventListener("click", removeSelected);
  el.undo.addEventListener("click", undo);
  el["place-centre"].addEventListener("click", placeArmedInMiddle);

  /* ---------------------------------------------------------------- pointer: the table */

  /** Client (CSS pixel) coordinates to normalized table coordinates. */
  function toTable(clientX, clientY) {
    const r = el["table-svg"].getBoundingClientRect();
    return { x: (clientX - r.left) / r.width, y: (clientY - r.top) / r.height, inside:
      clientX >= r.left && clientX <= r.right && clientY >= r.top && clientY <= r.bottom };
  }

  el["table-svg"].addEventListener("pointerdown", (ev) => {
    if (!app.state || !EDIT_STAGES.includes(app.state.stage) || ev.button !== 0 || app.busy) return;
    const svg = el["table-svg"];
    const q = toTable(ev.clientX, ev.clientY);
    const handle = ev.target.closest && ev.target.closest("[data-handle]");
    const g = ev.target.closest && ev.target.closest("g.placed");
    ev.preventDefault();
    if (handle && g) {
      const id = Number(g.dataset.object);
      app.drag = { kind: "rotate", id, pointerId: ev.pointerId, sx: ev.clientX, sy: ev.clientY, moved: false };
    } else if (g) {
      const id = Number(g.dataset.object);
      const p = app.placements.find((r) => r.object === id);
      app.selected = id;
      app.drag = { kind: "move", id, pointerId: ev.pointerId, sx: ev.clientX, sy: ev.clientY, moved: false,
        dx: q.x - p.x, dy: q.y - p.y, before: copyPlacements(app.placements) };
      render();
      g.focus({ preventScroll: true });
    } else if (app.armed !== null && app.state.stage === "arrange") {
      const id = app.armed;
      if (!placeNew(id, q.x, q.y)) return;
      // keep holding to adjust where it goes: the placement above is already one undo step
      app.drag = { kind: "move", id, pointerId: ev.pointerId, sx: ev.clientX, sy: ev.clientY, moved: true,
        placed: true, dx: 0, dy: 0, before: null };
      focusPlaced(id);
    } else {
      app.selected = null;
      render();
      svg.focus({ preventScroll: true });
      return;
    }
    try { svg.setPointerCapture(ev.pointerId); } catch (e) { /* synthetic pointers */ }
    svg.classList.add("dragging");
  });

  el["table-svg"].addEventListener("pointermove", (ev) => {
    const d = app.drag;
    if (!d || ev.pointerId !== d.pointerId) return;
    const far = Math.hypot(ev.clientX - d.sx, ev.clientY - d.sy) >= 2;
    if (!d.moved && !far) return;
    const q = toTable(ev.clientX, ev.clientY);
    if (d.kind === "rotate") {
      const p = app.placements.find((r) => r.object === d.id);
      if (!p) return;
      if (!d.moved) { remember(null); d.moved = true; }
      const ax = (q.x - p.x) * app.table.width, ay = (q.y - p.y) * app.table.height;
      if (Math.hypot(ax, ay) < 1e-6) return;
      let deg = Math.atan2(ax, -ay) * 180 / Math.PI;  // clockwise from image north
      if (ev.shiftKey) deg = Math.round(deg / 15) * 15;
      p.rotation = normRotation(Math.round(deg));
      render();
      return;
    }
    if (!d.moved) {
      if (d.before) { app.history.push(d.before); app.historyKey = null; }
      d.moved = true;
    }
    moveTo(d.id, q.x - d.dx, q.y - d.dy);
    render();
  });

  function endDrag(ev) {
    const d = app.drag;
    if (!d || ev.pointerId !== d.pointerId) return;
    app.drag = null;
    el["table-svg"].classList.remove("dragging");
    try { el["table-svg"].releasePointerCapture(ev.pointerId); } catch (e) { /* already released */ }
    if (d.moved) changed(); else render();
  }

  el["table-svg"].addEventListener("pointerup", endDrag);
  el["table-svg"].addEventListener("pointercancel", endDrag);

  /* ---------------------------------------------------------------- pointer: from the palette */

  function startPaletteDrag(ev, id) {
    if (ev.button !== 0 || isUsed(id) || !app.state || app.state.stage !== "arrange" || app.busy) return;
    app.paletteDrag = { id, pointerId: ev.pointerId, sx: ev.clientX, sy: ev.clientY, dragging: false };
  }

  function ghostTo(x, y) {
    const g = el["drag-ghost"];
    g.style.left = `${x}px`;
    g.style.top = `${y}px`;
  }

  document.addEventListener("pointermove", (ev) => {
    const d = app.paletteDrag;
    if (!d || ev.pointerId !== d.pointerId) return;
    if (!d.dragging) {
      if (Math.hypot(ev.clientX - d.sx, ev.clientY - d.sy) < DRAG_THRESHOLD) return;
      d.dragging = true;
      const o = app.objects.get(d.id);
      const [w, l] = sizeOf(d.id);
      const g = el["drag-ghost"];
      g.src = safePath(o.image);
      g.style.width = `${Math.max(8, w * app.screenScale)}px`;
      g.style.height = `${Math.max(8, l * app.screenScale)}px`;
      g.hidden = false;
      el["surface-outline"].classList.add("show");
    }
    ev.preventDefault();
    ghostTo(ev.clientX, ev.clientY);
  });

  function endPaletteDrag(ev, cancelled) {
    const d = app.paletteDrag;
    if (!d || ev.pointerId !== d.pointerId) return;
    app.paletteDrag = null;
    if (!d.dragging) return;            // a plain click: the click handler chooses the object
    app.suppressClick = true;
    setTimeout(() => { app.suppressClick = false; }, 0);
    el["drag-ghost"].hidden = true;
    const q = toTable(ev.clientX, ev.clientY);
    if (!cancelled && q.inside && placeNew(d.id, q.x, q.y)) focusPlaced(d.id);
    else render();
  }

  document.addEventListener("pointerup", (ev) => endPaletteDrag(ev, false));
  document.addEventListener("pointercancel", (ev) => endPaletteDrag(ev, true));

  /* ---------------------------------------------------------------- keys */

  document.addEventListener("keydown", (ev) => {
    if (!app.state || !EDIT_STAGES.includes(app.state.stage) || el["screen-task"].hidden || app.busy) return;
    const t = ev.target;
    const typing = t && (t.tagName === "INPUT" || t.tagName === "TEXTAREA" || t.tagName === "SELECT");
    if ((ev.ctrlKey || ev.metaKey) && !ev.altKey && !ev.shiftKey && (ev.key === "z" || ev.key === "Z")) {
      if (typing) return;
      ev.preventDefault();
      undo();
      return;
    }
    if (typing || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    // the keys act on the selection from the table, its objects, the selection's own buttons or the page itself
    const onTable = t === el["table-svg"] || t === document.body || t === document.documentElement ||
      (t && t.closest && (t.closest("g.placed") || t.closest("#selection")));
    if (t === el["table-svg"] && (ev.key === "Enter" || ev.key === " ") && app.armed !== null) {
      ev.preventDefault();
      placeArmedInMiddle();
      return;
    }
    if (ev.key === "Escape") {
      if (app.armed !== null) { app.armed = null; updatePalette(); updateControls(); }
      else if (app.selected !== null) { app.selected = null; render(); }
      return;
    }
    if (app.selected === null || !onTable) return;
    const step = ev.shiftKey ? 4 * NUDGE : NUDGE;
    const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (moves[ev.key]) {
      ev.preventDefault();
      nudge(moves[ev.key][0], moves[ev.key][1]);
    } else if (ev.key === "r" || ev.key === "R") {
      ev.preventDefault();
      rotateSelected(ev.shiftKey ? -15 : 15);
    } else if (ev.key === "PageUp" || ev.key === "PageDown") {
      ev.preventDefault();
      rotateSelected(ev.key === "PageUp" ? -15 : 15);
    } else if ((ev.key === "Delete" || ev.key === "Backspace") && app.state.stage === "arrange") {
      ev.preventDefault();
      removeSelected();
    }
  });

  /* ---------------------------------------------------------------- rating */

  function updateRating() {
    const out = el["rating-value"];
    if (app.ratingMoved) {
      out.textContent = `${el.rating.value} / 100`;
      out.classList.remove("unset");
      el.rating.classList.remove("unset");
    } else {
      out.textContent = "not set yet (move the slider)";
      out.classList.add("unset");
      el.rating.classList.add("unset");
    }
  }

  function ratingTouched() {
    app.ratingMoved = true;
    updateRating();
    updateControls();
  }

  el.rating.addEventListener("input", ratingTouched);
  el.rating.addEventListener("change", ratingTouched);

  /* ---------------------------------------------------------------- drafts */

  function scheduleDraft() {
    const stage = app.state && app.state.stage;
    if (!EDIT_STAGES.includes(stage)) return;
    clearTimeout(app.draftTimer);
    el["save-status"].textContent = "Saving…";
    app.draftTimer = setTimeout(saveDraft, DRAFT_DELAY_MS);
  }

  function draftBody() {
    const st = app.state;
    return { trial: st.trial, stage: st.stage, placements: copyPlacements(app.placements) };
  }

  /** PUT the placements in progress; one request at a time (a change meanwhile is sent after it). */
  async function saveDraft() {
    app.draftTimer = null;
    const st = app.state;
    if (!st || !EDIT_STAGES.includes(st.stage) || app.busy) return;
    if (app.draftInFlight) { app.draftAgain = true; return; }
    app.draftInFlight = true;
    app.draftAgain = false;
    try {
      await api("PUT", "/api/draft", draftBody());
      if (app.state === st && !app.draftAgain && app.draftTimer === null) el["save-status"].textContent = "Draft saved";
    } catch (e) {
      // the stage moved on meanwhile (a submit in flight or answered): the draft no longer matters
      if (app.state !== st || app.busy) return;
      if (e.status === 401) { showStart(); return; }
      if (e.status === 409) { await reloadAfterConflict(e.detail); return; }
      el["save-status"].textContent = "Not saved";
      showError(e.detail);
    } finally {
      app.draftInFlight = false;
      if (app.draftAgain && app.state === st && !app.busy) saveDraft();
    }
  }

  /** Leaving the page with a change not yet saved: send it now (keepalive outlives the page). */
  function flushDraft() {
    if (app.draftTimer === null || !app.state || !EDIT_STAGES.includes(app.state.stage) || app.busy) return;
    clearTimeout(app.draftTimer);
    app.draftTimer = null;
    try {
      fetch("/api/draft", { method: "PUT", keepalive: true, credentials: "same-origin",
        headers: { "Content-Type": "application/json" }, body: JSON.stringify(draftBody()) });
    } catch (e) { /* the page is going away */ }
  }

  window.addEventListener("pagehide", flushDraft);
  document.addEventListener("visibilitychange", () => { if (document.visibilityState === "hidden") flushDraft(); });

  async function reloadAfterConflict(detail) {
    showError(`${detail} (the study moved on, perhaps in another tab: showing where you are now)`);
    try {
      showState(await api("GET", "/api/state"));
    } catch (e) {
      if (e.status === 401) showStart(); else showError(e.detail);
    }
  }

  /* ---------------------------------------------------------------- submit */

  el.submit.addEventListener("click", async () => {
    if (app.busy || !canSubmit()) return;
    const st = app.state;
    const body = { submission: freshId(), trial: st.trial, stage: st.stage };
    if (EDIT_STAGES.includes(st.stage)) body.placements = copyPlacements(app.placements);
    else body.rating = Number(el.rating.value);
    clearTimeout(app.draftTimer);
    app.draftTimer = null;
    app.busy = true;
    el.submit.setAttribute("aria-busy", "true");
    updateControls();
    clearError();
    try {
      const next = await api("POST", "/api/submit", body);
      app.busy = false;
      showState(next);
    } catch (e) {
      app.busy = false;
      if (e.status === 401) showStart();
      else if (e.status === 409) await reloadAfterConflict(e.detail);
      else showError(e.detail);
    } finally {
      el.submit.removeAttribute("aria-busy");
      if (app.state) updateControls();
    }
  });

  boot();
})();

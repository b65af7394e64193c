// matflow studio: the session's status arrives as server-sent events
// (api/events); the page shows the newest render, the selection over it
// and the scene's maps, and sends selections and changes as small JSON
// requests. Every request carries the page's token, if it was opened with
// one (?token=...).

const token = new URLSearchParams(location.search).get("token");
const withToken = (url) => {
  if (!token) return url;
  return `${url}${url.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}`;
};
const $ = (id) => document.getElementById(id);

const state = { status: null, image: null, photo: null, dims: [1, 1] };

// ---- requests -------------------------------------------------------------

async function post(path, body, type = "application/json") {
  const headers = { "content-type": type };
  if (token) headers.authorization = `Bearer ${token}`;
  const r = await fetch(path, {
    method: "POST",
    headers,
    body: type === "application/json" ? JSON.stringify(body ?? {}) : body,
  });
  if (!r.ok) throw new Error((await r.text()).trim() || `${r.status}`);
  return r.status === 204 ? null : r.json();
}

// A file picked in the input `id` is posted to `path`; `then` gets the
// answer.
function onFile(id, path, type, then = () => {}) {
  $(id).addEventListener("change", async () => {
    const f = $(id).files[0];
    if (!f) return;
    try {
      showError(null);
      await then(await post(path, await f.arrayBuffer(), type));
    } catch (e) {
      showError(e);
    }
  });
}

function showError(e) {
  $("error").textContent = e ? e.message ?? String(e) : "";
}

function loadImage(url) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error(`cannot load ${url}`));
    img.src = withToken(url);
  });
}

// ---- drawing --------------------------------------------------------------

function sizeCanvases(w, h) {
  if (state.dims[0] === w && state.dims[1] === h) return;
  state.dims = [w, h];
  for (const id of ["before", "view", "overlay"]) {
    $(id).width = w;
    $(id).height = h;
  }
  $("frame").style.aspectRatio = `${w} / ${h}`;
}

// The view: the "after" image, with the photo ("before") left of the split.
function draw() {
  const [w, h] = state.dims;
  const before = $("before").getContext("2d");
  const view = $("view").getContext("2d");
  before.clearRect(0, 0, w, h);
  view.clearRect(0, 0, w, h);
  if (state.photo) before.drawImage(state.photo, 0, 0, w, h);
  const after = state.image ?? state.photo;
  if (after) view.drawImage(after, 0, 0, w, h);
  // The split is a clip on the view canvas, so the before image shows
  // through its left part.
  const split = Number($("split").value);
  $("view").style.clipPath = split > 0 ? `inset(0 0 0 ${split * 100}%)` : "none";
}

async function refreshOverlay() {
  try {
    const img = await loadImage(`api/images/selection.png?n=${Date.now()}`);
    const ctx = $("overlay").getContext("2d");
    ctx.clearRect(0, 0, ...state.dims);
    ctx.drawImage(img, 0, 0, ...state.dims);
    state.overlay = img;
    drawMarkers();
  } catch (e) {
    showError(e);
  }
}

// Inserted objects' anchors, over the selection.
function drawMarkers() {
  const ctx = $("overlay").getContext("2d");
  const [w] = state.dims;
  const r = Math.max(2, w / 90);
  ctx.lineWidth = Math.max(1, w / 256);
  for (const [i, o] of (state.objects ?? []).entries()) {
    const [x, y] = drag?.object === i && drag.to ? drag.to : o.anchor;
    ctx.strokeStyle = "#ffd166";
    ctx.beginPath();
    ctx.arc(x, y, r, 0, 2 * Math.PI);
    ctx.stroke();
  }
}

// ---- the session's status -------------------------------------------------

let shownKey = "";
let mapsShown = false;

async function onStatus(s) {
  if (state.status && s.input !== state.status.input) {
    // Another photo: its maps and images replace these.
    mapsShown = false;
    shownKey = "";
    state.photo = null;
    state.image = null;
    $("maps").replaceChildren();
    $("loss-box").hidden = true;
  }
  state.status = s;
  $("input").textContent = s.input;
  const where = s.stage ? ` — ${s.stage}${s.total ? ` ${s.done}/${s.total}` : s.done ? ` step ${s.done}` : ""}` : "";
  $("status").textContent = `${s.state}: ${s.message}${where}`;
  $("status").className = `status ${s.state}`;
  const p = $("progress");
  if (s.state === "running" && s.total > 0) {
    p.max = s.total;
    p.value = s.done;
  } else if (s.state === "running") {
    p.removeAttribute("value");
  } else {
    p.max = 1;
    p.value = 1;
  }
  $("selected").textContent = s.selected ? `${s.selected} px selected` : "nothing selected";
  $("undo").disabled = s.history.length === 0;
  $("redo").disabled = s.redo === 0;
  const list = $("history");
  list.replaceChildren(
    ...s.history.map((h) => {
      const li = document.createElement("li");
      li.textContent = h;
      return li;
    }),
  );
  const pick = $("envmap");
  const have = [...pick.options].map((o) => o.value);
  for (const name of s.envmaps) {
    if (!have.includes(name)) pick.append(new Option(name, name));
  }
  if (state.pickEnvmap && s.envmaps.includes(state.pickEnvmap)) {
    pick.value = state.pickEnvmap;
    state.pickEnvmap = null;
  }
  const meshPick = $("obj-mesh");
  const meshes = [...meshPick.options].map((o) => o.value);
  for (const name of s.meshes) {
    if (!meshes.includes(name)) meshPick.append(new Option(name, name));
  }
  if (state.pickMesh && s.meshes.includes(state.pickMesh)) {
    meshPick.value = state.pickMesh;
    state.pickMesh = null;
  }
  if (JSON.stringify(s.objects) !== JSON.stringify(state.objects)) {
    state.objects = s.objects;
    showObjects();
  }
  drawLoss(s);
  if (document.activeElement !== $("geometry")) $("geometry").value = s.geometry || "auto";
  $("geometry-taken").textContent = s.geometry_taken
    ? `${s.geometry_taken}; changing it runs the recovery again`
    : "";
  if (s.width && s.height) sizeCanvases(s.width, s.height);
  if (!mapsShown && s.maps.length) {
    mapsShown = true;
    showMaps(s);
    if (s.maps.includes("photo")) {
      state.photo = await loadImage("api/maps/photo.png");
      draw();
    }
    refreshOverlay();
  }
  // The recovery shows its fit so far several times in one generation.
  const shot = s.image === "recovery" ? `/${s.recovery_shots}` : "";
  const key = `${s.shown}/${s.image}${shot}`;
  if (s.image && key !== shownKey) {
    shownKey = key;
    const img = await loadImage(`api/images/${s.image}.png?g=${s.shown}${shot ? `&n=${s.recovery_shots}` : ""}`);
    // A newer status may have come while this one loaded.
    if (shownKey === key) {
      state.image = img;
      draw();
      document.body.dataset.shown = key;
    }
  }
  document.body.dataset.state = s.state;
}

// The recovery's loss per step, on a log scale.
function drawLoss(s) {
  if (!s.loss.length) return;
  $("loss-box").hidden = false;
  const c = $("loss");
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  const logs = s.loss.map((v) => Math.log10(Math.max(v, 1e-12)));
  const lo = Math.min(...logs);
  const hi = Math.max(...logs);
  const span = hi - lo || 1;
  ctx.strokeStyle = "#61afef";
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  logs.forEach((v, i) => {
    const x = 4 + (i / Math.max(1, logs.length - 1)) * (c.width - 8);
    const y = 4 + (1 - (v - lo) / span) * (c.height - 8);
    if (i === 0) ctx.moveTo(x, y);
    else ctx.lineTo(x, y);
  });
  ctx.stroke();
  const last = s.loss[s.loss.length - 1];
  $("loss-caption").textContent = `${s.loss_stage} loss: ${last.toPrecision(4)} after ${s.loss.length} steps (log scale)`;
}

function showMaps(s) {
  const maps = $("maps");
  maps.replaceChildren();
  for (const name of s.maps) {
    const fig = document.createElement("figure");
    const img = document.createElement("img");
    img.src = withToken(`api/maps/${name}.png`);
    img.alt = name;
    img.style.aspectRatio = `${s.width} / ${s.height}`;
    const cap = document.createElement("figcaption");
    cap.textContent = name;
    fig.append(img, cap);
    maps.append(fig);
  }
}

function listen() {
  const es = new EventSource(withToken("api/events"));
  es.onmessage = (m) => {
    if (m.data) onStatus(JSON.parse(m.data)).catch(showError);
  };
  es.onerror = () => {
    $("status").textContent = "no answer from the studio; retrying…";
    $("status").className = "status failed";
  };
}

// ---- selection ------------------------------------------------------------

const tool = () => document.querySelector("input[name=tool]:checked").value;

function toImage(e) {
  const r = $("overlay").getBoundingClientRect();
  const [w, h] = state.dims;
  return [((e.clientX - r.left) * w) / r.width, ((e.clientY - r.top) * h) / r.height];
}

const modeOf = (e) => (e.altKey ? "remove" : e.shiftKey ? "add" : "set");

async function select(path, body) {
  try {
    showError(null);
    await post(path, body);
    await refreshOverlay();
  } catch (e) {
    showError(e);
  }
}

let drag = null;

// The object whose marker is under (x, y), if any.
function objectAt(x, y) {
  const r = Math.max(3, state.dims[0] / 60);
  return (state.objects ?? []).findIndex((o) => Math.hypot(o.anchor[0] - x, o.anchor[1] - y) <= r);
}

$("overlay").addEventListener("pointerdown", (e) => {
  const [x, y] = toImage(e);
  const mode = modeOf(e);
  const hit = objectAt(x, y);
  if (hit >= 0) {
    // On a marker: drag moves the object; shift-drag turns it (two
    // turns across the image's width).
    drag = { object: hit, turn: e.shiftKey, from: [x, y] };
  } else if (tool() === "place") {
    sendObjects([...(state.objects ?? []), objectFromControls([x, y])]);
  } else if (tool() === "object") {
    select("api/select", { x, y, mode, tolerance: Number($("tolerance").value) });
  } else if (tool() === "rect") {
    drag = { x0: x, y0: y, mode };
  } else {
    // A brush adds (alt: erases) dabs along the stroke.
    drag = { points: [[x, y]], mode: e.altKey ? "remove" : "add" };
  }
  $("overlay").setPointerCapture(e.pointerId);
});

$("overlay").addEventListener("pointermove", (e) => {
  if (!drag) return;
  const [x, y] = toImage(e);
  if (drag.object !== undefined) {
    drag.to = [x, y];
    const ctx = $("overlay").getContext("2d");
    ctx.clearRect(0, 0, ...state.dims);
    if (state.overlay) ctx.drawImage(state.overlay, 0, 0, ...state.dims);
    drawMarkers();
  } else if (drag.points) {
    drag.points.push([x, y]);
    const ctx = $("overlay").getContext("2d");
    ctx.fillStyle = drag.mode === "remove" ? "rgba(0,0,0,0.4)" : "rgba(40,160,255,0.43)";
    ctx.beginPath();
    ctx.arc(x, y, Number($("radius").value), 0, 2 * Math.PI);
    ctx.fill();
  } else {
    drag.x1 = x;
    drag.y1 = y;
  }
});

// The wheel over a marker scales its object (a tenth per notch).
$("overlay").addEventListener(
  "wheel",
  (e) => {
    const [x, y] = toImage(e);
    const hit = objectAt(x, y);
    if (hit < 0) return;
    e.preventDefault();
    const k = e.deltaY < 0 ? 1.1 : 1 / 1.1;
    sendObjects(
      state.objects.map((o, i) =>
        i === hit ? { ...o, scale: Math.min(20, Math.max(0.01, Math.round(o.scale * k * 1000) / 1000)) } : o,
      ),
    );
  },
  { passive: false },
);

$("overlay").addEventListener("pointerup", (e) => {
  if (!drag) return;
  const d = drag;
  drag = null;
  const [x, y] = toImage(e);
  if (d.object !== undefined) {
    if (d.to && d.turn) {
      const turn = (o) => ((((o.rotate + (x - d.from[0]) * (360 / state.dims[0]) * 2) % 360) + 540) % 360) - 180;
      sendObjects(state.objects.map((o, i) => (i === d.object ? { ...o, rotate: Math.round(turn(o)) } : o)));
    } else if (d.to) {
      const objs = state.objects.map((o, i) => (i === d.object ? { ...o, anchor: [x, y] } : o));
      sendObjects(objs);
    }
  } else if (d.points) {
    select("api/select/brush", { points: d.points, radius: Number($("radius").value), mode: d.mode });
  } else {
    select("api/select/rect", { x0: d.x0, y0: d.y0, x1: x, y1: y, mode: d.mode });
  }
});

$("clear").addEventListener("click", () => select("api/select/clear"));

onFile("mask", "api/select/mask?mode=set", "image/png", refreshOverlay);

// ---- changes --------------------------------------------------------------

for (const [id, digits] of [["tolerance", 2], ["radius", 0], ["hue", 0], ["sat", 2], ["val", 2], ["rough", 2], ["metal", 2], ["rotation", 0], ["exposure", 1], ["obj-rough", 2], ["obj-metal", 2], ["obj-ior", 2], ["obj-scale", 2], ["obj-rotate", 0], ["glass-t", 2], ["glass-ior", 2]]) {
  const show = () => ($(`${id}-v`).textContent = Number($(id).value).toFixed(digits));
  $(id).addEventListener("input", show);
  show();
}
$("rough").addEventListener("input", () => ($("set-rough").checked = true));
$("metal").addEventListener("input", () => ($("set-metal").checked = true));
$("albedo").addEventListener("input", () => ($("set-albedo").checked = true));
$("split").addEventListener("input", draw);

// The change the controls describe: only what is set or moved.
function change() {
  const c = {};
  if ($("set-albedo").checked) {
    const hex = $("albedo").value;
    c.albedo = [1, 3, 5].map((i) => Math.round((parseInt(hex.slice(i, i + 2), 16) / 255) * 1000) / 1000);
  }
  if (Number($("hue").value) !== 0) c.hue_shift = Number($("hue").value);
  if (Number($("sat").value) !== 1) c.saturation_scale = Number($("sat").value);
  if (Number($("val").value) !== 1) c.value_scale = Number($("val").value);
  if ($("set-rough").checked) c.roughness = Number($("rough").value);
  if ($("set-metal").checked) c.metallic = Number($("metal").value);
  return c;
}

async function act(path, body) {
  try {
    showError(null);
    await post(path, body);
  } catch (e) {
    showError(e);
  }
}

$("apply").addEventListener("click", () => act("api/edit", change()));
$("relight").addEventListener("click", () =>
  act("api/light", {
    envmap: $("envmap").value || undefined,
    rotation: Number($("rotation").value),
    exposure: Number($("exposure").value),
  }),
);
onFile("envmap-file", "api/light/envmap", "application/octet-stream", (r) => (state.pickEnvmap = r.envmap));
$("glass").addEventListener("click", () =>
  act("api/glass", { ior: Number($("glass-ior").value), transmission: Number($("glass-t").value) }),
);
$("geometry").addEventListener("change", () => act("api/geometry", { complete: $("geometry").value }));
$("undo").addEventListener("click", () => act("api/undo"));
$("redo").addEventListener("click", () => act("api/redo"));

// ---- inserted objects -----------------------------------------------------

const gamma = (hex) => [1, 3, 5].map((i) => Math.round((parseInt(hex.slice(i, i + 2), 16) / 255) * 1000) / 1000);

function objectFromControls(anchor) {
  const type = $("obj-type").value;
  const material = { type, albedo: gamma($("obj-albedo").value), roughness: Number($("obj-rough").value) };
  if (type === "principled") material.metallic = Number($("obj-metal").value);
  if (type === "glass") {
    material.ior = Number($("obj-ior").value);
    delete material.albedo;
  }
  return {
    mesh: $("obj-mesh").value,
    anchor: anchor.map((v) => Math.round(v * 10) / 10),
    scale: Number($("obj-scale").value),
    rotate: Number($("obj-rotate").value),
    material,
  };
}

// The page's form of an object the server read back (nulls dropped).
function clean(o) {
  const material = Object.fromEntries(Object.entries(o.material).filter(([, v]) => v !== null));
  return { ...o, material };
}

async function sendObjects(objects) {
  await act("api/insert", { objects: objects.map(clean) });
}

function showObjects() {
  const list = $("objects");
  list.replaceChildren(
    ...(state.objects ?? []).map((o, i) => {
      const li = document.createElement("li");
      li.textContent = `${o.mesh} (${o.material.type}) at ${o.anchor.map((v) => v.toFixed(0)).join(", ")}, ×${o.scale}`;
      const update = document.createElement("button");
      update.textContent = "set from controls";
      update.onclick = () =>
        sendObjects(state.objects.map((p, j) => (j === i ? objectFromControls(p.anchor) : p)));
      const remove = document.createElement("button");
      remove.textContent = "remove";
      remove.onclick = () => sendObjects(state.objects.filter((_, j) => j !== i));
      li.append(update, remove);
      return li;
    }),
  );
  const ctx = $("overlay").getContext("2d");
  ctx.clearRect(0, 0, ...state.dims);
  if (state.overlay) ctx.drawImage(state.overlay, 0, 0, ...state.dims);
  drawMarkers();
}

onFile("mesh-file", "api/insert/mesh", "application/octet-stream", (r) => (state.pickMesh = r.mesh));

onFile("open", "api/open", "application/octet-stream");

$("dl-png").href = withToken("api/images/result.png");
$("dl-exr").href = withToken("api/images/result.exr");
$("export").href = withToken("api/export.tar");

listen();

// matflow studio: polls the session until its pipeline has run, then shows
// the photo and its maps. Every request carries the page's token, if the
// page was opened with one (?token=...).

const token = new URLSearchParams(location.search).get("token");
const withToken = (url) => (token ? `${url}?token=${encodeURIComponent(token)}` : url);

const statusEl = document.getElementById("status");
const mapsEl = document.getElementById("maps");
const inputEl = document.getElementById("input");
document.getElementById("export").href = withToken("api/pipeline.yaml");

function showMaps(s) {
  mapsEl.replaceChildren();
  for (const name of s.maps) {
    const fig = document.createElement("figure");
    const img = document.createElement("img");
    img.src = withToken(`api/maps/${name}.png`);
    img.alt = name;
    // Shown at a readable size whatever the image's own (pixels kept sharp).
    img.style.aspectRatio = `${s.width} / ${s.height}`;
    const cap = document.createElement("figcaption");
    cap.textContent = name;
    fig.append(img, cap);
    mapsEl.append(fig);
  }
}

async function poll() {
  let s;
  try {
    const r = await fetch(withToken("api/session"));
    if (!r.ok) throw new Error(`${r.status} ${await r.text()}`);
    s = await r.json();
  } catch (e) {
    statusEl.textContent = `no answer: ${e.message}`;
    statusEl.className = "status failed";
    setTimeout(poll, 2000);
    return;
  }
  inputEl.textContent = s.input;
  statusEl.textContent = `${s.state}: ${s.message}`;
  statusEl.className = `status ${s.state}`;
  if (s.state === "ready") {
    showMaps(s);
  } else if (s.state === "running") {
    setTimeout(poll, 500);
  }
}

poll();

// dray dashboard. Plain JavaScript, no build step. The server is the coordinator's
// RenderService behind /api/ (docs/dashboard.md): this file only shows what it answers.
"use strict";

const TERMINAL = new Set(["SUCCEEDED", "FAILED", "CANCELLED"]);
// A cancel asks first: the first click arms the row's button, the second cancels.
const CSRF = { "X-Dray-Csrf": "1" };
// A running job's image is fetched again at most this often.
const IMAGE_REFRESH_MS = 1000;

const $ = (id) => document.getElementById(id);
const state = {
  events: null,          // EventSource of snapshots
  pageToken: "",         // ListJobs page shown ("" = newest)
  pageHistory: [],
  lastJobs: "",          // last jobs JSON rendered (skip identical snapshots)
  lastWorkers: "",
  workerNames: new Map(), // worker id -> name, from the last workers list
  selected: null,        // job id
  armed: null,           // the job whose cancel button asks for confirmation
  selectedState: null,   // its last state
  jobs: [],              // the rows of the last snapshot
  jobEvents: null,       // EventSource of the selected job's progress
  image: { busy: false, again: false, last: 0, url: null, version: 0, timer: null },
};

function esc(s) {
  return String(s ?? "").replace(/[&<>"']/g, (c) =>
    ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

function fmtCount(n) {
  if (n == null) return "";
  if (n >= 1e9) return (n / 1e9).toFixed(2) + " G";
  if (n >= 1e6) return (n / 1e6).toFixed(2) + " M";
  if (n >= 1e4) return (n / 1e3).toFixed(1) + " k";
  return String(n);
}

function fmtBytes(n) {
  if (n == null) return "";
  const u = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (n >= 1024 && i < u.length - 1) { n /= 1024; i++; }
  return (i ? n.toFixed(1) : n) + " " + u[i];
}

function fmtSecs(s) {
  if (s == null) return "";
  if (s < 10) return s.toFixed(1) + " s";
  s = Math.round(s);
  if (s < 60) return s + " s";
  const m = Math.floor(s / 60);
  if (m < 60) return m + " m " + String(s % 60).padStart(2, "0") + " s";
  return Math.floor(m / 60) + " h " + String(m % 60).padStart(2, "0") + " m";
}

async function api(path, options = {}) {
  const r = await fetch(path, { credentials: "same-origin", ...options });
  if (r.status === 401) {
    showLogin();
  }
  return r;
}

async function errorText(r) {
  try {
    const e = await r.json();
    return `${e.code}: ${e.message}`;
  } catch (_) {
    return `HTTP ${r.status}`;
  }
}

// ---- session ----

async function boot() {
  const r = await fetch("/api/session", { credentials: "same-origin" });
  const s = await r.json();
  $("logout").hidden = !s.auth_required;
  if (s.auth_required && !s.authenticated) {
    showLogin();
  } else {
    showApp();
  }
}

function showLogin() {
  stopEvents();
  $("app").hidden = true;
  $("login").hidden = false;
  $("logout").hidden = true;
  $("token").focus();
}

function showApp() {
  $("login").hidden = true;
  $("app").hidden = false;
  startEvents();
}

$("login-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  $("login-error").textContent = "";
  const r = await fetch("/api/login", {
    method: "POST",
    credentials: "same-origin",
    headers: { "Content-Type": "application/json", ...CSRF },
    body: JSON.stringify({ token: $("token").value }),
  });
  if (!r.ok) {
    $("login-error").textContent = await errorText(r);
    return;
  }
  $("token").value = "";
  $("logout").hidden = false;
  showApp();
});

$("logout").addEventListener("click", async () => {
  await fetch("/api/logout", { method: "POST", credentials: "same-origin", headers: CSRF });
  showLogin();
});

// ---- live snapshots ----

function stopEvents() {
  if (state.events) state.events.close();
  state.events = null;
  if (state.jobEvents) state.jobEvents.close();
  state.jobEvents = null;
  $("live").classList.remove("on");
  $("live").textContent = "offline";
}

function startEvents() {
  if (state.events) state.events.close();
  const q = new URLSearchParams({ jobs: "100" });
  if (state.pageToken) q.set("page_token", state.pageToken);
  const es = new EventSource("/api/events?" + q);
  state.events = es;
  es.addEventListener("open", () => {
    $("live").classList.add("on");
    $("live").textContent = "live";
  });
  es.addEventListener("snapshot", (e) => {
    const s = JSON.parse(e.data);
    renderJobs(s.jobs);
    renderWorkers(s.workers);
  });
  es.addEventListener("failed", (e) => {
    $("submit-error").textContent = e.data;
  });
  es.addEventListener("error", async () => {
    $("live").classList.remove("on");
    $("live").textContent = "reconnecting";
    // A session that expired: EventSource cannot see the 401, the session endpoint can.
    const r = await fetch("/api/session", { credentials: "same-origin" }).catch(() => null);
    if (r && r.ok) {
      const s = await r.json();
      if (s.auth_required && !s.authenticated) showLogin();
    }
  });
  if (state.selected) selectJob(state.selected);
}

// ---- jobs ----

function progressCell(j) {
  if (!j.tiles_total) return "";
  const pct = Math.floor((100 * j.tiles_done) / j.tiles_total);
  return `<progress max="${j.tiles_total}" value="${j.tiles_done}"></progress> ${pct}%`;
}

function renderJobs(page) {
  const json = JSON.stringify(page);
  if (json === state.lastJobs) return;
  state.lastJobs = json;
  const jobs = page.jobs;
  state.jobs = jobs;
  state.nextPageToken = page.next_page_token;
  const running = jobs.filter((j) => !TERMINAL.has(j.state)).length;
  $("jobs-count").textContent = `${jobs.length} shown, ${running} active`;
  $("summary").textContent = `${running} active job${running === 1 ? "" : "s"}`;
  $("jobs-empty").hidden = jobs.length > 0;
  const rows = jobs.map((j) => {
    const name = j.label ? `${esc(j.label)} <small>${esc(j.id)}</small>` : esc(j.id);
    // A frame of a job group: its frame and group beside the id.
    const title = j.group === undefined ? name
      : `${name} <small class="group" title="job group ${esc(j.group)}">frame ${j.frame} of ${esc(j.group)}</small>`;
    const cancel = TERMINAL.has(j.state)
      ? ""
      : state.armed === j.id
        ? `<button class="cancel armed" data-cancel="${esc(j.id)}" data-armed="1" title="CancelJob">really cancel?</button>
           <button class="keep" data-keep="1" title="do not cancel">keep</button>`
        : `<button class="cancel" data-cancel="${esc(j.id)}" title="CancelJob (asks first)">cancel</button>`;
    return `<tr data-id="${esc(j.id)}" data-state="${esc(j.state)}"${j.id === state.selected ? ' class="selected"' : ""}>
      <td>${title}</td>
      <td>${esc(j.scene)}</td>
      <td><span class="state ${esc(j.state)}" title="${esc(j.error)}">${esc(j.state)}</span></td>
      <td>${progressCell(j)}</td>
      <td class="num">${fmtCount(j.rays_traced)}</td>
      <td class="num">${fmtSecs(j.elapsed_s)}</td>
      <td class="num">${TERMINAL.has(j.state) ? "" : fmtSecs(j.eta_s)}</td>
      <td>${j.width}×${j.height}, ${j.spp} spp ${esc(j.integrator)}</td>
      <td>${cancel}</td>
    </tr>`;
  });
  $("jobs").tBodies[0].innerHTML = rows.join("");
  const pager = [];
  if (state.pageHistory.length) pager.push('<button data-page="newest">newest</button>');
  if (page.next_page_token) {
    pager.push(`<button data-page="${esc(page.next_page_token)}">older jobs</button>`);
  }
  $("jobs-pager").innerHTML = pager.join("");
  if (state.selected) {
    const j = jobs.find((x) => x.id === state.selected);
    if (j) renderJobHeader(j);
  }
}

$("jobs").addEventListener("click", async (e) => {
  const keep = e.target.closest("button[data-keep]");
  if (keep) {
    e.stopPropagation();
    state.armed = null;
    state.lastJobs = "";
    renderJobs({ jobs: state.jobs, next_page_token: state.nextPageToken });
    return;
  }
  const cancel = e.target.closest("button[data-cancel]");
  if (cancel && !cancel.dataset.armed) {
    e.stopPropagation();
    state.armed = cancel.dataset.cancel;
    state.lastJobs = "";
    renderJobs({ jobs: state.jobs, next_page_token: state.nextPageToken });
    return;
  }
  if (cancel) {
    e.stopPropagation();
    state.armed = null;
    cancel.disabled = true;
    const r = await api(`/api/jobs/${encodeURIComponent(cancel.dataset.cancel)}/cancel`, {
      method: "POST",
      headers: CSRF,
    });
    if (!r.ok) $("submit-error").textContent = await errorText(r);
    return;
  }
  const row = e.target.closest("tr[data-id]");
  if (row) selectJob(row.dataset.id);
});

$("jobs-pager").addEventListener("click", (e) => {
  const b = e.target.closest("button[data-page]");
  if (!b) return;
  if (b.dataset.page === "newest") {
    state.pageHistory = [];
    state.pageToken = "";
  } else {
    state.pageHistory.push(state.pageToken);
    state.pageToken = b.dataset.page;
  }
  state.lastJobs = "";
  startEvents();
});

$("submit-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const f = new FormData(e.target);
  const num = (k) => (f.get(k) === "" ? undefined : Number(f.get(k)));
  const body = {
    scene: f.get("scene").trim(),
    width: num("width"),
    height: num("height"),
    spp: num("spp"),
    integrator: f.get("integrator"),
    max_depth: num("max_depth"),
    domains: num("domains") ?? 0,
    schedule: f.get("schedule"),
    seed: num("seed") ?? 0,
    label: f.get("label"),
    fov: num("fov"),
    orthographic: f.get("orthographic") === "on",
    aperture: f.get("aperture") ?? "",
    focus_distance: num("focus_distance"),
    env_map: (f.get("env_map") ?? "").trim(),
    env_rotation: num("env_rotation"),
    env_intensity: num("env_intensity"),
    time: num("time"),
    animation: (f.get("animation") ?? "").trim(),
    frames: (f.get("frames") ?? "").trim(),
    fps: num("fps"),
    noise_threshold: num("noise_threshold"),
    clamp_indirect: num("clamp_indirect"),
    sun_size: num("sun_size"),
    aovs: f.getAll("aov"),
  };
  // "X,Y,Z" and "AZ,EL" fields as arrays of numbers; the coordinator checks the values.
  for (const [k, n] of [["look_from", 3], ["look_at", 3], ["up", 3], ["orbit", 2], ["focus_on", 3], ["sun_color", 3]]) {
    const text = (f.get(k) ?? "").trim();
    if (text === "") continue;
    const v = text.split(",").map((t) => Number(t.trim()));
    if (v.length !== n || v.some((x) => !Number.isFinite(x))) {
      $("submit-error").textContent = `${k}: expected ${n} comma-separated numbers, got "${text}"`;
      return;
    }
    body[k] = v;
  }
  // The sun: "AZ,EL" or "AZ,EL,IRRADIANCE".
  const sunText = (f.get("sun") ?? "").trim();
  if (sunText !== "") {
    const v = sunText.split(",").map((t) => Number(t.trim()));
    if (v.length < 2 || v.length > 3 || v.some((x) => !Number.isFinite(x))) {
      $("submit-error").textContent = `sun: expected AZ,EL or AZ,EL,IRRADIANCE, got "${sunText}"`;
      return;
    }
    body.sun = v;
  }
  $("submit-error").textContent = "";
  $("submit-button").disabled = true;
  try {
    const r = await api("/api/jobs", {
      method: "POST",
      headers: { "Content-Type": "application/json", ...CSRF },
      body: JSON.stringify(body),
    });
    if (!r.ok) {
      $("submit-error").textContent = await errorText(r);
      return;
    }
    const { id } = await r.json();
    selectJob(id);
  } finally {
    $("submit-button").disabled = false;
  }
});

// ---- the selected job ----

function selectJob(id) {
  const changed = state.selected !== id;
  state.selected = id;
  for (const tr of $("jobs").tBodies[0].rows) {
    tr.classList.toggle("selected", tr.dataset.id === id);
  }
  if (state.jobEvents) state.jobEvents.close();
  if (changed) {
    state.selectedState = null;
    $("job-title").textContent = id;
    $("job-title").classList.remove("muted");
    $("job-stats").innerHTML = "";
    $("job-workers").innerHTML = "";
    const img = $("preview");
    img.hidden = true;
    img.removeAttribute("src");
    img.dataset.version = "0";
    delete img.dataset.samples;
    state.image.version = 0;
    $("preview-caption").textContent = "";
    const j = state.jobs.find((x) => x.id === id);
    if (j) renderJobHeader(j);
    $("job-operator").innerHTML = "";
  }
  drayOperator.show(id);
  const es = new EventSource(`/api/jobs/${encodeURIComponent(id)}/events`);
  state.jobEvents = es;
  es.addEventListener("progress", (e) => {
    const p = JSON.parse(e.data);
    if (p.state !== state.selectedState) drayOperator.show(id);
    state.selectedState = p.state;
    renderProgress(p);
    if (p.state === "RUNNING" || p.state === "SUCCEEDED") refreshImage(p.state === "SUCCEEDED");
    if (TERMINAL.has(p.state)) {
      es.close();
      if (p.state !== "SUCCEEDED") {
        $("preview-caption").textContent = p.state === "FAILED" ? p.error : "cancelled";
      }
    }
  });
  es.addEventListener("failed", (e) => {
    $("preview-caption").textContent = e.data;
    es.close();
  });
}

function renderJobHeader(j) {
  const t = $("job-title");
  t.textContent = `${j.label || j.id} — ${j.scene} ${j.width}×${j.height}, ${j.spp} spp, ${j.state}`;
  t.dataset.state = j.state;
}

function renderProgress(p) {
  const s = p.stats || {};
  const rays = s.rays || [];
  const kinds = ["camera", "shadow", "reflection", "refraction", "diffuse", "AO"];
  const rows = [
    ["state", p.state + (p.error ? ` (${p.error})` : "")],
    ["tiles", `${p.tiles_done} / ${p.tiles_total}`],
    ["samples", p.passes_total ? `${p.samples_done} per pixel, pass ${p.passes_done} of ${p.passes_total}` : ""],
    ["elapsed", fmtSecs(p.elapsed_s)],
    ["ETA", TERMINAL.has(p.state) ? "" : fmtSecs(p.eta_s)],
    ["rays traced", fmtCount(p.rays_traced)],
    ["rays in flight", fmtCount(p.rays_in_flight)],
    ["rays by kind", kinds.map((k, i) => (rays[i] ? `${k} ${fmtCount(rays[i])}` : "")).filter(Boolean).join(", ")],
    ["triangles", fmtCount(s.triangles)],
    ["domains", s.domains],
    ["workers", s.workers],
    ["schedule", s.schedule],
    ["placement", s.placement],
    ["domain loads", s.domain_loads != null ? `${s.domain_loads} (${fmtSecs(s.domain_load_seconds)}), ${s.domains_warm} warm, ${s.evictions} evicted` : ""],
    ["rays exchanged", fmtCount(s.rays_exchanged)],
    ["queue peak", fmtCount(s.queue_peak)],
    ["scheduler rounds", s.scheduler_rounds],
    ["traffic", s.traffic_bytes ? fmtBytes(s.traffic_bytes) : ""],
    ["CPU", s.cpu_seconds ? fmtSecs(s.cpu_seconds) : ""],
    ["tiles retried", s.tiles_retried || ""],
  ];
  $("job-stats").innerHTML = rows
    .filter(([, v]) => v !== "" && v != null)
    .map(([k, v]) => `<dt>${esc(k)}</dt><dd>${esc(v)}</dd>`)
    .join("");
  const detail = s.workers_detail || [];
  $("job-workers").innerHTML = detail.length
    ? "<thead><tr><th>worker</th><th>rays traced</th><th>domain loads</th><th>warm</th><th>evictions</th><th>idle</th><th>queue peak</th></tr></thead><tbody>" +
      detail.map((w) => `<tr><td>${workerLabel(w.worker_id, state.workerNames.get(w.worker_id))}</td><td class="num">${fmtCount(w.rays_traced)}</td>
        <td class="num">${w.domain_loads}</td><td class="num">${w.domains_warm}</td><td class="num">${w.evictions}</td>
        <td class="num">${fmtSecs(w.idle_seconds)}</td><td class="num">${fmtCount(w.queue_peak)}</td></tr>`).join("") +
      "</tbody>"
    : "";
}

// The selected job's image: one fetch at a time, at most every IMAGE_REFRESH_MS, and
// always once more after the job has succeeded.
function refreshImage(final) {
  const im = state.image;
  if (im.busy) {
    im.again = true;
    return;
  }
  const wait = im.last + IMAGE_REFRESH_MS - Date.now();
  if (wait > 0 && !final) {
    if (!im.timer) im.timer = setTimeout(() => { im.timer = null; refreshImage(false); }, wait);
    return;
  }
  const id = state.selected;
  im.busy = true;
  im.last = Date.now();
  fetchImage(id).finally(() => {
    im.busy = false;
    if (im.again) {
      im.again = false;
      refreshImage(final);
    }
  });
}

async function fetchImage(id) {
  const r = await api(`/api/jobs/${encodeURIComponent(id)}/image.png?v=${Date.now()}`);
  if (id !== state.selected) return;
  const caption = $("preview-caption");
  if (r.status === 409) {
    // A job that failed or was cancelled meanwhile keeps its caption.
    if (!TERMINAL.has(state.selectedState)) {
      caption.textContent = "the image is shown once the job has an image to show";
    }
    return;
  }
  if (!r.ok) {
    caption.textContent = await errorText(r);
    return;
  }
  const blob = await r.blob();
  if (id !== state.selected) return;
  const url = URL.createObjectURL(blob);
  const img = $("preview");
  await new Promise((resolve) => {
    img.onload = resolve;
    img.onerror = resolve;
    img.src = url;
  });
  if (state.image.url) URL.revokeObjectURL(state.image.url);
  state.image.url = url;
  img.hidden = false;
  state.image.version += 1;
  img.dataset.version = String(state.image.version);
  const samples = r.headers.get("x-dray-samples");
  if (samples != null) img.dataset.samples = samples;
  const w = r.headers.get("x-dray-width"), h = r.headers.get("x-dray-height");
  const final = r.headers.get("x-dray-final") === "true";
  caption.textContent = `${w}×${h}` + (samples != null
    ? `, ${samples} samples per pixel${final ? "" : " so far"}` : "");
}

// ---- workers ----

function renderWorkers(workers) {
  if (workers === undefined) return;
  const json = JSON.stringify(workers);
  if (json === state.lastWorkers) return;
  state.lastWorkers = json;
  renderWorkerTable(workers);
}

// A worker as the logs name it: its name (dray worker --name) and, smaller, its id.
function workerLabel(id, name) {
  return name ? `<span class="worker-name">${esc(name)}</span> <small class="muted">${esc(id)}</small>` : esc(id);
}

function renderWorkerTable(workers) {
  const list = workers.workers || [];
  state.workerNames = new Map(list.filter((w) => w.name).map((w) => [w.id, w.name]));
  const colour = new Map(list.map((w, i) => [w.id, `o${i % 12}`]));
  $("workers-count").textContent = `${list.length} registered`;
  $("workers-empty").hidden = list.length > 0;
  $("workers").tBodies[0].innerHTML = list.map((w) => {
    const resident = (w.domains || []).filter((d) => d.resident || d.owned);
    const chips = resident.map((d) =>
      `<span class="chip ${d.owned ? colour.get(w.id) : "onone"}" title="job ${esc(d.job_id)}, domain ${d.domain}: ${d.resident ? "resident" : "not loaded"}, ${d.owned ? "owned" : "not owned"}, ${d.rays_queued} rays queued">${d.domain}</span>`).join("");
    const budget = w.memory_budget_bytes ? " / " + fmtBytes(w.memory_budget_bytes) : "";
    return `<tr data-worker="${esc(w.id)}" data-name="${esc(w.name || "")}">
      <td><span class="chip ${colour.get(w.id)}">&nbsp;</span> ${workerLabel(w.id, w.name)}</td>
      <td title="${esc(w.hostname)}">${esc(w.address)}</td><td>${esc(w.state)}</td>
      <td><meter min="0" max="${w.memory_budget_bytes || w.memory_used_bytes || 1}" value="${w.memory_used_bytes}"></meter>
        ${fmtBytes(w.memory_used_bytes)}${budget}</td>
      <td class="num">${fmtCount(w.rays_queued)}</td>
      <td class="num">${fmtCount(Math.round(w.rays_per_second || 0))}</td>
      <td>${esc((w.jobs || []).join(", "))}</td>
      <td class="chips">${chips}</td>
    </tr>`;
  }).join("");
  // Each running job's domains: coloured by (first) owner, with the rays waiting.
  $("ownership").innerHTML = (workers.jobs || []).map((j) => {
    const cells = j.domains.map((d) => {
      const owner = d.worker_ids.length ? colour.get(d.worker_ids[0]) || "onone" : "onone";
      const owners = d.worker_ids.length ? d.worker_ids.map((id) => state.workerNames.has(id) ? `${state.workerNames.get(id)} (${id})` : id).join(", ") : "any worker";
      return `<span class="domain ${owner}" title="domain ${d.domain}: ${esc(owners)}">${d.domain}<span class="waiting">${fmtCount(d.rays_queued)}</span></span>`;
    }).join("");
    return `<div class="ownership-job" data-job="${esc(j.job_id)}">
      <div class="legend">${esc(j.job_id)}: ${esc(j.schedule)}, routing table v${j.routing_version}, attempt ${j.attempt}</div>
      <div class="domains">${cells}</div></div>`;
  }).join("") || '<p class="muted">No job running on workers.</p>';
}

boot().catch((e) => {
  $("login-error").textContent = String(e);
  $("login").hidden = false;
});

// dray dashboard: the operator side of the selected job (issue 42, docs/dashboard.md):
// retry, requeue, pause and resume buttons, downloads of the finished PNG and EXR, the
// attempts, the job it was retried from, and its event log. Each button is one
// RenderService call behind /api/jobs/{id}/...; app.js calls drayOperator.show(id)
// when a job is selected and whenever its state changes.
"use strict";

const drayOperator = (() => {
  const el = (id) => document.getElementById(id);
  const escape = (s) => String(s ?? "").replace(/[&<>"']/g, (c) =>
    ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
  const HEADERS = { "X-Dray-Csrf": "1" };
  let shown = null;  // the job id shown
  let busy = false;

  function time(ms) {
    return ms == null ? "" : new Date(ms).toLocaleTimeString();
  }

  function actions(j) {
    const id = encodeURIComponent(j.id);
    const b = [];
    if (j.state === "FAILED" || j.state === "CANCELLED") {
      b.push(`<button type="button" data-op="retry" title="RetryJob: a new job with the same spec">retry</button>`);
    }
    if (!["QUEUED", "PAUSED"].includes(j.state)) {
      b.push(`<button type="button" data-op="requeue" title="RequeueJob: stop it if it runs, queue it again">requeue</button>`);
    }
    if (j.state === "QUEUED") b.push(`<button type="button" data-op="pause" title="PauseJob">pause</button>`);
    if (j.state === "PAUSED") b.push(`<button type="button" data-op="resume" title="ResumeJob">resume</button>`);
    if (j.state === "SUCCEEDED") {
      b.push(`<a class="download" href="/api/jobs/${id}/download/image.png" download>PNG</a>`);
      b.push(`<a class="download" href="/api/jobs/${id}/download/image.exr" download>EXR</a>`);
    }
    return b.join(" ");
  }

  function render(j) {
    const lines = [`priority ${j.priority}`, `${j.attempts} attempt${j.attempts === 1 ? "" : "s"}`];
    const from = j.retried_from
      ? ` · retried from <a href="#" data-job="${escape(j.retried_from)}">${escape(j.retried_from)}</a>` : "";
    el("job-operator").innerHTML =
      `<p class="job-actions" data-state="${escape(j.state)}">${actions(j)}</p>
       <p class="muted">${escape(lines.join(" · "))}${from}</p>
       <ol id="job-events">${(j.events || []).map((e) =>
         `<li data-kind="${escape(e.kind)}"><time>${escape(time(e.at_ms))}</time>
          <b>${escape(e.kind.toLowerCase().replace("_", " "))}</b> ${escape(e.message)}</li>`).join("")}</ol>`;
  }

  async function show(id) {
    shown = id;
    const r = await fetch(`/api/jobs/${encodeURIComponent(id)}`, { credentials: "same-origin" });
    if (!r.ok || shown !== id) return;
    render(await r.json());
  }

  async function act(op) {
    if (busy || !shown) return;
    busy = true;
    const id = shown;
    try {
      const r = await fetch(`/api/jobs/${encodeURIComponent(id)}/${op}`, {
        method: "POST", credentials: "same-origin", headers: HEADERS,
      });
      const body = await r.json().catch(() => ({}));
      if (!r.ok) {
        el("submit-error").textContent = body.message || `${op}: HTTP ${r.status}`;
        return;
      }
      // A retry or requeue answers the new job: show it.
      if (body.id && typeof selectJob === "function") selectJob(body.id);
      else show(id);
    } finally {
      busy = false;
    }
  }

  document.addEventListener("DOMContentLoaded", () => {
    el("job-operator").addEventListener("click", (e) => {
      const b = e.target.closest("button[data-op]");
      if (b) {
        b.disabled = true;
        act(b.dataset.op);
        return;
      }
      const link = e.target.closest("a[data-job]");
      if (link && typeof selectJob === "function") {
        e.preventDefault();
        selectJob(link.dataset.job);
      }
    });
  });

  return { show };
})();

// RoGUENeRF web page: scenes, fine-tuning, compare. Plain JS, no build step, no third-party code.
// Talks only to this server's public API (same origin), with the same bearer key as any client.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const KEY_ITEM = "roguenerf.apiKey";
  const JOBS_ITEM = "roguenerf.jobs";

  // ------------------------------------------------------------------ API access
  class ApiError extends Error {
    constructor(status, code, message) { super(message); this.status = status; this.code = code; }
  }

  function apiKey() { return sessionStorage.getItem(KEY_ITEM) || ""; }

  function authHeaders(extra) {
    const headers = new Headers(extra || {});
    const key = apiKey();
    if (key) headers.set("Authorization", "Bearer " + key);
    return headers;
  }

  async function errorFrom(response) {
    let code = "http_" + response.status, message = response.status + " " + response.statusText;
    try {
      const body = await response.json();
      if (body && body.error) { code = body.error.code; message = body.error.message; }
    } catch (_) { /* not JSON: keep the status line */ }
    return new ApiError(response.status, code, message);
  }

  async function api(path, options = {}) {
    const response = await fetch(path, { ...options, headers: authHeaders(options.headers),
                                         credentials: "omit", cache: "no-store" });
    if (!response.ok) throw await errorFrom(response);
    return response;
  }
  const getJSON = async (path) => (await api(path)).json();

  function showError(id, err) {
    const box = $(id);
    if (!err) { box.hidden = true; return; }
    const msg = box.querySelector(".msg"), code = box.querySelector(".code");
    if (msg) { msg.textContent = err.message; code.textContent = err.code || ""; }
    else box.textContent = err.message;
    box.hidden = false;
    if (err.status === 401) $("key-state").textContent = "the server needs an API key";
  }

  // ------------------------------------------------------------------ formatting
  const fmt = {
    psnr: (v) => (v === null || v === undefined) ? "∞" : Number(v).toFixed(2),
    ssim: (v) => Number(v).toFixed(4),
    seconds(s) {
      if (s === null || s === undefined) return "–";
      s = Math.max(0, Math.round(s));
      const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
      return h ? `${h} h ${m} min` : m ? `${m} min ${r} s` : `${r} s`;
    },
    date: (iso) => iso ? new Date(iso).toLocaleString() : "–",
    version: (v) => v === 0 ? "v0 (default)" : "v" + v,
  };

  // ------------------------------------------------------------------ screens
  const SCREENS = ["scenes", "finetune", "compare"];
  function route() {
    const name = SCREENS.includes(location.hash.slice(1)) ? location.hash.slice(1) : "scenes";
    for (const s of SCREENS) {
      $(s).hidden = s !== name;
      const link = $("nav-" + s);
      if (s === name) link.setAttribute("aria-current", "page"); else link.removeAttribute("aria-current");
    }
    if (name === "compare") loadViews();
    if (name === "finetune") showSceneJob();
  }

  // ------------------------------------------------------------------ scenes
  let scenes = [];           // every loaded scene, newest first
  let nextCursor = null;

  async function loadScenes(more = false) {
    try {
      const url = "/scenes?limit=50" + (more && nextCursor ? "&cursor=" + encodeURIComponent(nextCursor) : "");
      const page = await getJSON(url);
      scenes = more ? scenes.concat(page.items) : page.items;
      nextCursor = page.next_cursor;
      showError("scenes-error", null);
      renderScenes();
    } catch (err) { showError("scenes-error", err); }
  }

  function cell(row, content, label) {
    const td = document.createElement("td");
    if (label) td.dataset.label = label;
    if (content instanceof Node) td.append(content); else td.textContent = content;
    row.append(td);
    return td;
  }

  function renderScenes() {
    const body = $("scenes-table").querySelector("tbody");
    body.replaceChildren();
    for (const s of scenes) {
      const tr = document.createElement("tr");
      tr.dataset.scene = s.id;
      const code = document.createElement("code"); code.textContent = s.id;
      cell(tr, code, "Scene");
      cell(tr, `${s.views} (${s.train_views} / ${s.test_views})`, "Views");
      cell(tr, `${s.width}×${s.height}`, "Size");
      cell(tr, fmt.version(s.active_version), "Checkpoint");
      cell(tr, fmt.date(s.created_at), "Created");
      cell(tr, s.active_job ? "running or queued" : "–", "Job");
      const actions = cell(tr, "", "Open");
      for (const [label, screen] of [["Fine-tune", "finetune"], ["Compare", "compare"]]) {
        const b = document.createElement("button");
        b.type = "button"; b.textContent = label;
        b.setAttribute("aria-label", `${label} scene ${s.id.slice(0, 8)}`);
        b.addEventListener("click", () => { selectScene(s.id); location.hash = screen; });
        actions.append(b);
      }
      body.append(tr);
    }
    $("scenes-empty").hidden = scenes.length > 0;
    $("scenes-more").hidden = !nextCursor;
    for (const id of ["ft-scene", "cmp-scene"]) {
      const select = $(id), keep = select.value;
      select.replaceChildren(...scenes.map((s) => new Option(
        `${s.id.slice(0, 8)} · ${s.views} views · ${fmt.version(s.active_version)}`, s.id)));
      if (keep && scenes.some((s) => s.id === keep)) select.value = keep;
    }
  }

  function selectScene(id) { $("ft-scene").value = id; $("cmp-scene").value = id; }

  function upload(event) {
    event.preventDefault();
    const archive = $("upload-archive").files[0];
    if (!archive) return;
    const form = new FormData();
    form.append("archive", archive, archive.name);
    const ckpt = $("upload-checkpoint").files[0];
    if (ckpt) form.append("checkpoint", ckpt, ckpt.name);
    const xhr = new XMLHttpRequest();       // fetch cannot report upload progress
    const bar = $("upload-progress"), status = $("upload-status"), button = $("upload-submit");
    bar.value = 0; status.textContent = "uploading…"; button.disabled = true;
    showError("scenes-error", null);
    xhr.upload.addEventListener("progress", (e) => {
      if (e.lengthComputable) {
        bar.value = Math.round(100 * e.loaded / e.total);
        status.textContent = `${bar.value}% of ${(e.total / 1e6).toFixed(1)} MB` + (bar.value === 100 ? ", checking the scene…" : "");
      }
    });
    xhr.addEventListener("loadend", async () => {
      button.disabled = false;
      if (xhr.status === 201) {
        const scene = JSON.parse(xhr.responseText);
        bar.value = 100;
        status.textContent = `registered ${scene.id} (${scene.views} views)`;
        $("upload-form").reset();
        bar.value = 100;
        await loadScenes();
        selectScene(scene.id);
        return;
      }
      status.textContent = "failed";
      let err = new ApiError(xhr.status, "network_error", "the upload did not reach the server");
      if (xhr.status) {
        try {
          const body = JSON.parse(xhr.responseText);
          err = new ApiError(xhr.status, body.error.code, body.error.message);
        } catch (_) { err = new ApiError(xhr.status, "http_" + xhr.status, `${xhr.status} ${xhr.statusText}`); }
      }
      showError("scenes-error", err);
    });
    xhr.open("POST", "/scenes");
    const key = apiKey();
    if (key) xhr.setRequestHeader("Authorization", "Bearer " + key);
    xhr.send(form);
  }

  // ------------------------------------------------------------------ fine-tuning
  let jobTimer = null, jobShown = null, losses = new Map();

  function rememberJob(sceneId, jobId) {
    const jobs = JSON.parse(sessionStorage.getItem(JOBS_ITEM) || "{}");
    jobs[sceneId] = jobId;
    sessionStorage.setItem(JOBS_ITEM, JSON.stringify(jobs));
  }
  function rememberedJob(sceneId) { return JSON.parse(sessionStorage.getItem(JOBS_ITEM) || "{}")[sceneId]; }

  async function showSceneJob() {
    const id = $("ft-scene").value;
    if (!id) return;
    try {
      const scene = await getJSON("/scenes/" + id);
      const jobId = scene.active_job || rememberedJob(id);
      if (jobId) watchJob(jobId); else { stopWatching(); $("job").hidden = true; $("ft-cancel").disabled = true; }
    } catch (err) { showError("ft-error", err); }
  }

  async function startJob(event) {
    event.preventDefault();
    const id = $("ft-scene").value, unit = $("ft-unit").value, value = Number($("ft-budget").value);
    const body = unit === "steps" ? { steps: Math.round(value) } : { minutes: value };
    try {
      const job = await (await api(`/scenes/${id}/finetune`, {
        method: "POST", body: JSON.stringify(body), headers: { "Content-Type": "application/json" } })).json();
      showError("ft-error", null);
      rememberJob(id, job.id);
      watchJob(job.id);
    } catch (err) { showError("ft-error", err); }
  }

  async function cancelJob() {
    if (!jobShown) return;
    try { renderJob(await (await api(`/jobs/${jobShown}/cancel`, { method: "POST" })).json()); }
    catch (err) { showError("ft-error", err); }
  }

  function stopWatching() { if (jobTimer) clearTimeout(jobTimer); jobTimer = null; }

  function watchJob(jobId) {
    stopWatching();
    if (jobShown !== jobId) { losses = new Map(); jobShown = jobId; }
    const poll = async () => {
      try {
        const job = await getJSON("/jobs/" + jobId);
        if (jobShown !== jobId) return;
        renderJob(job);
        if (job.state === "queued" || job.state === "running") jobTimer = setTimeout(poll, 1000);
        else { jobTimer = null; loadScenes(); }
      } catch (err) { showError("ft-error", err); jobTimer = setTimeout(poll, 3000); }
    };
    poll();
  }

  function renderJob(job) {
    $("job").hidden = false;
    $("job-id").textContent = job.id;
    $("job-state").textContent = job.state + (job.cancel_requested && job.state === "running" ? " (cancelling)" : "");
    $("job").dataset.state = job.state;
    $("job-step").textContent = job.step ? `${job.step}` + (job.total_steps ? ` of ${job.total_steps}` : "") : "–";
    $("job-loss").textContent = job.loss === null ? "–" : job.loss.toPrecision(4);
    $("job-eta").textContent = job.state === "running" ? fmt.seconds(job.eta_s) : job.state === "queued" ? "waiting for a worker" : "–";
    $("job-version").textContent = job.checkpoint_version ? fmt.version(job.checkpoint_version) : "–";
    $("job-progress").value = job.progress;
    $("ft-cancel").disabled = !(job.state === "queued" || job.state === "running");
    for (const [step, loss] of job.recent_losses) losses.set(step, loss);
    drawLoss();
    const error = $("job-error");
    error.hidden = !job.error;
    error.textContent = job.error ? `${job.state}: ${job.error.message} (${job.error.code})` : "";
    const table = $("job-metrics"), body = table.querySelector("tbody");
    body.replaceChildren();
    const rows = [];
    if (job.before) rows.push(["render", job.before.render], ["enhanced, before fine-tuning", job.before.enhanced]);
    if (job.after) rows.push(["enhanced, after fine-tuning", job.after.enhanced]);
    for (const [label, m] of rows) {
      if (!m) continue;
      const tr = document.createElement("tr");
      const th = document.createElement("th"); th.scope = "row"; th.textContent = label; tr.append(th);
      cell(tr, fmt.psnr(m.psnr)); cell(tr, fmt.ssim(m.ssim));
      body.append(tr);
    }
    table.hidden = rows.length === 0;
  }

  function drawLoss() {
    const pts = [...losses.entries()].sort((a, b) => a[0] - b[0]);
    const svg = $("loss-curve");
    if (!pts.length) {
      $("loss-line").setAttribute("points", ""); svg.setAttribute("aria-label", "loss curve: no steps yet");
      $("loss-caption").textContent = "Training loss per step"; return;
    }
    const steps = pts.map((p) => p[0]), values = pts.map((p) => p[1]);
    const s0 = Math.min(...steps), s1 = Math.max(...steps), lo = Math.min(...values), hi = Math.max(...values);
    const x = (s) => s1 === s0 ? 160 : 8 + 304 * (s - s0) / (s1 - s0);
    const y = (v) => hi === lo ? 60 : 112 - 104 * (v - lo) / (hi - lo);
    let points = pts.map(([s, v]) => `${x(s).toFixed(1)},${y(v).toFixed(1)}`).join(" ");
    if (pts.length === 1) points = `8,${y(values[0]).toFixed(1)} 312,${y(values[0]).toFixed(1)}`;
    $("loss-line").setAttribute("points", points);
    svg.dataset.points = String(pts.length);
    svg.setAttribute("aria-label", `loss curve: ${pts.length} steps, from ${values[0].toPrecision(3)} to ${values[values.length - 1].toPrecision(3)}`);
    $("loss-caption").textContent = `Training loss per step: steps ${s0}–${s1}, loss ${lo.toPrecision(3)} (bottom) to ${hi.toPrecision(3)} (top)`;
  }

  // ------------------------------------------------------------------ compare
  const enhancedCache = new Map();   // "scene:view:version" -> {blob, neighbours, seconds, note}
  let views = [], viewsOf = null, compareToken = 0;
  const urls = { render: null, enhanced: null, photo: null };

  async function loadViews() {
    const id = $("cmp-scene").value;
    if (!id) return;
    if (viewsOf === id && views.length) return showView();
    try {
      views = (await getJSON(`/scenes/${id}/views?split=test`)).items;
      viewsOf = id;
      $("cmp-view").replaceChildren(...views.map((v) => new Option(`${v.name} (#${v.index})`, String(v.index))));
      showError("cmp-error", null);
      if (!views.length) { $("cmp-status").textContent = "this scene has no test views"; return; }
      await showView();
    } catch (err) { showError("cmp-error", err); }
  }

  function setUrl(kind, blob) {
    if (urls[kind]) URL.revokeObjectURL(urls[kind]);
    urls[kind] = URL.createObjectURL(blob);
    return urls[kind];
  }

  async function score(sceneId, index, blob) {
    const form = new FormData();
    form.append("image", blob, "image.png");
    return (await api(`/scenes/${sceneId}/views/${index}/score`, { method: "POST", body: form })).json();
  }

  async function enhanced(sceneId, view, render, version) {
    const key = `${sceneId}:${view.index}:${version}`;
    if (enhancedCache.has(key)) return { ...enhancedCache.get(key), cached: true };
    const depth = await (await api(`/scenes/${sceneId}/views/${view.index}/depth`)).blob();
    const form = new FormData();
    form.append("scene_id", sceneId);
    form.append("render", render, "render.png");
    form.append("depth", depth, "depth.npy");
    form.append("camera", JSON.stringify(view.camera));
    const response = await api("/enhance", { method: "POST", body: form });
    const entry = {
      blob: await response.blob(),
      neighbours: (response.headers.get("X-Neighbours") || "").split(",").filter(Boolean),
      seconds: Number(response.headers.get("X-Enhance-Seconds")),
      version: response.headers.get("X-Checkpoint-Version"),
      note: response.headers.get("X-Enhance-Note"),
    };
    enhancedCache.set(`${sceneId}:${view.index}:${entry.version}`, entry);
    return { ...entry, cached: false };
  }

  async function showView() {
    const sceneId = $("cmp-scene").value, index = Number($("cmp-view").value);
    const view = views.find((v) => v.index === index);
    if (!view) return;
    const token = ++compareToken;
    const status = $("cmp-status");
    status.textContent = `enhancing ${view.name}…`;
    $("compare").dataset.ready = "false";
    for (const id of ["m-render-psnr", "m-render-ssim", "m-enhanced-psnr", "m-enhanced-ssim"]) $(id).textContent = "…";
    try {
      const scene = await getJSON(`/scenes/${sceneId}`);
      const [render, photo] = await Promise.all([
        api(`/scenes/${sceneId}/views/${index}/render`).then((r) => r.blob()),
        view.has_photo ? api(`/scenes/${sceneId}/views/${index}/photo`).then((r) => r.blob()) : null]);
      const out = await enhanced(sceneId, view, render, scene.active_version);
      if (token !== compareToken) return;
      $("img-render").src = setUrl("render", render);
      $("img-enhanced").src = setUrl("enhanced", out.blob);
      if (photo) $("img-photo").src = setUrl("photo", photo); else $("img-photo").removeAttribute("src");
      $("cmp-neighbours").textContent = out.neighbours.join(", ") || "none";
      $("cmp-version").textContent = fmt.version(Number(out.version));
      $("cmp-seconds").textContent = out.cached ? `${out.seconds.toFixed(2)} s (cached result)` : `${out.seconds.toFixed(2)} s`;
      $("cmp-note").textContent = out.note || "–";
      updateStage();
      if (photo) {
        const [mr, me] = await Promise.all([score(sceneId, index, render), score(sceneId, index, out.blob)]);
        if (token !== compareToken) return;
        $("m-render-psnr").textContent = fmt.psnr(mr.psnr); $("m-render-ssim").textContent = fmt.ssim(mr.ssim);
        $("m-enhanced-psnr").textContent = fmt.psnr(me.psnr); $("m-enhanced-ssim").textContent = fmt.ssim(me.ssim);
      }
      status.textContent = `${view.name}: ${view.width}×${view.height}`;
      showError("cmp-error", null);
      $("compare").dataset.ready = "true";
    } catch (err) {
      if (token !== compareToken) return;
      status.textContent = "";
      showError("cmp-error", err);
    }
  }

  function updateStage() {
    const pick = { render: urls.render, enhanced: urls.enhanced, photo: urls.photo };
    const left = pick[$("cmp-left").value], right = pick[$("cmp-right").value];
    if (left) $("cmp-before").src = left;
    if (right) $("cmp-after").src = right;
    applyZoom();
  }

  function applyZoom() {
    const zoom = Number($("cmp-zoom").value);
    const view = views.find((v) => v.index === Number($("cmp-view").value));
    if (!view) return;
    for (const id of ["cmp-before", "cmp-after"]) {
      $(id).style.width = view.width * zoom + "px";
      $(id).style.height = view.height * zoom + "px";
    }
  }

  let divider = 50;
  function setDivider(percent) {
    divider = Math.min(100, Math.max(0, percent));
    const p = divider.toFixed(2);
    $("cmp-after").style.clipPath = `inset(0 0 0 ${p}%)`;
    $("cmp-handle").style.left = p + "%";
    const handle = $("cmp-handle");
    handle.setAttribute("aria-valuenow", String(Math.round(divider)));
    handle.setAttribute("aria-valuetext", `${Math.round(divider)}% ${$("cmp-left").value}, ${Math.round(100 - divider)}% ${$("cmp-right").value}`);
  }

  function initSlider() {
    const stage = $("stage"), handle = $("cmp-handle");
    let dragging = false;
    const fromEvent = (e) => {
      const rect = stage.getBoundingClientRect();
      setDivider(100 * (e.clientX - rect.left) / rect.width);
    };
    stage.addEventListener("pointerdown", (e) => {
      dragging = true; stage.setPointerCapture(e.pointerId); fromEvent(e); handle.focus({ preventScroll: true });
    });
    stage.addEventListener("pointermove", (e) => { if (dragging) fromEvent(e); });
    const stop = () => { dragging = false; };
    stage.addEventListener("pointerup", stop);
    stage.addEventListener("pointercancel", stop);
    handle.addEventListener("keydown", (e) => {
      const step = e.shiftKey ? 10 : 1;
      const moves = { ArrowLeft: -step, ArrowDown: -step, ArrowRight: step, ArrowUp: step, PageDown: -10, PageUp: 10 };
      if (e.key in moves) setDivider(divider + moves[e.key]);
      else if (e.key === "Home") setDivider(0);
      else if (e.key === "End") setDivider(100);
      else return;
      e.preventDefault();
    });
    setDivider(50);
  }

  // ------------------------------------------------------------------ API key
  function initKey() {
    const input = $("api-key"), state = $("key-state");
    const show = () => { state.textContent = apiKey() ? "key set for this tab" : "no key"; };
    $("key-form").addEventListener("submit", (e) => {
      e.preventDefault();
      if (input.value) sessionStorage.setItem(KEY_ITEM, input.value.trim());
      input.value = "";
      show();
      reload();
    });
    $("key-forget").addEventListener("click", () => { sessionStorage.removeItem(KEY_ITEM); show(); });
    show();
  }

  function reload() { loadScenes().then(route); }

  document.addEventListener("DOMContentLoaded", () => {
    initKey();
    initSlider();
    $("upload-form").addEventListener("submit", upload);
    $("scenes-more").addEventListener("click", () => loadScenes(true));
    $("finetune-form").addEventListener("submit", startJob);
    $("ft-cancel").addEventListener("click", cancelJob);
    $("ft-scene").addEventListener("change", () => { $("cmp-scene").value = $("ft-scene").value; showSceneJob(); });
    $("cmp-scene").addEventListener("change", () => { $("ft-scene").value = $("cmp-scene").value; loadViews(); });
    $("cmp-view").addEventListener("change", showView);
    $("cmp-left").addEventListener("change", () => { updateStage(); setDivider(divider); });
    $("cmp-right").addEventListener("change", () => { updateStage(); setDivider(divider); });
    $("cmp-zoom").addEventListener("change", applyZoom);
    window.addEventListener("hashchange", route);
    reload();
  });
})();

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
  const getJSON = async (path, signal) => (await api(path, { signal })).json();

  /** Fetch ``path`` (with the key) and hand it to the browser as a file called ``filename``. */
  async function download(path, filename) {
    const blob = await (await api(path)).blob();
    saveBlob(blob, filename);
  }
  function saveBlob(blob, filename) {
    const url = URL.createObjectURL(blob), a = document.createElement("a");
    a.href = url; a.download = filename; a.hidden = true;
    document.body.append(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60_000);
  }
  const fileSafe = (text) => String(text).replace(/[\\/:*?"<>|\u0000-\u001f]+/g, "_").slice(0, 100) || "file";

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
    /** X-Colour-Offset (R, G, B added to match the neighbour photos' colour), or none sent. */
    colour: (rgb) => rgb && rgb.length === 3
      ? "yes, offset " + ["R", "G", "B"].map((c, k) => `${c} ${rgb[k] >= 0 ? "+" : "−"}${Math.abs(rgb[k]).toFixed(4)}`).join(" ")
      : "no (the neighbours did not agree enough)",
    /** X-Trust (share of the enhancer's change kept) and X-Neighbour-Agreement, or none sent. */
    trust: (kept, agree) => Number.isFinite(kept) && Number.isFinite(agree)
      ? `${Math.round(kept * 100)} % (the neighbours agree on ${Math.round(agree * 100)} % of the view)`
      : "all (fewer than two neighbours to compare)",
  };

  // ------------------------------------------------------------------ screens
  const SCREENS = ["scenes", "finetune", "compare", "videos"];
  function route() {
    const name = SCREENS.includes(location.hash.slice(1)) ? location.hash.slice(1) : "scenes";
    for (const s of SCREENS) {
      $(s).hidden = s !== name;
      const link = $("nav-" + s);
      if (s === name) link.setAttribute("aria-current", "page"); else link.removeAttribute("aria-current");
    }
    if (name === "compare") loadViews();
    if (name === "finetune") showSceneJob();
    if (name === "videos") loadVideos(); else stopVideoPolling();
  }

  // ------------------------------------------------------------------ scenes
  let scenes = [];           // every loaded scene, newest first
  let nextCursor = null;

  const sceneOf = (id) => scenes.find((s) => s.id === id);
  /** A scene's name for people: its name, else the start of its id. */
  function sceneLabel(idOrScene) {
    const s = typeof idOrScene === "string" ? sceneOf(idOrScene) : idOrScene;
    if (!s) return String(idOrScene).slice(0, 8);
    return s.name || s.id.slice(0, 8);
  }
  /** Name (big) over id (small): how a scene is shown in tables. */
  function sceneBadge(idOrScene) {
    const id = typeof idOrScene === "string" ? idOrScene : idOrScene.id;
    const s = sceneOf(id) || (typeof idOrScene === "string" ? null : idOrScene);
    const wrap = document.createElement("span"); wrap.className = "scene-badge";
    const name = document.createElement("span"); name.className = "scene-name";
    name.textContent = !s ? "–" : s.name || "(no name)";
    const code = document.createElement("code"); code.className = "scene-id"; code.textContent = id;
    wrap.append(name, code);
    return wrap;
  }

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
      cell(tr, sceneBadge(s), "Scene");
      cell(tr, `${s.views} (${s.train_views} / ${s.test_views})`, "Views");
      cell(tr, `${s.width}×${s.height}`, "Size");
      cell(tr, fmt.version(s.active_version), "Checkpoint");
      cell(tr, fmt.date(s.created_at), "Created");
      cell(tr, s.active_job ? "running or queued" : "–", "Job");
      const actions = cell(tr, "", "Open");
      for (const [label, screen] of [["Fine-tune", "finetune"], ["Compare", "compare"]]) {
        const b = document.createElement("button");
        b.type = "button"; b.textContent = label;
        b.setAttribute("aria-label", `${label} scene ${sceneLabel(s)}`);
        b.addEventListener("click", () => { selectScene(s.id); location.hash = screen; });
        actions.append(b);
      }
      const rename = document.createElement("button");
      rename.type = "button"; rename.textContent = "Rename";
      rename.setAttribute("aria-label", `Rename scene ${sceneLabel(s)}`);
      rename.addEventListener("click", () => renameScene(s));
      actions.append(rename);
      const del = document.createElement("button");
      del.type = "button"; del.textContent = "Delete"; del.className = "danger";
      del.setAttribute("aria-label", `Delete scene ${sceneLabel(s)}`);
      del.addEventListener("click", () => deleteScene(s));
      actions.append(del);
      body.append(tr);
    }
    $("scenes-empty").hidden = scenes.length > 0;
    $("scenes-more").hidden = !nextCursor;
    for (const id of ["ft-scene", "cmp-scene"]) {
      const select = $(id), keep = select.value;
      select.replaceChildren(...scenes.map((s) => new Option(
        `${sceneLabel(s)} · ${s.id.slice(0, 8)} · ${s.views} views · ${fmt.version(s.active_version)}`, s.id)));
      if (keep && scenes.some((s) => s.id === keep)) select.value = keep;
    }
    showCheckpointDownload();
  }

  function selectScene(id) { $("ft-scene").value = id; $("cmp-scene").value = id; showCheckpointDownload(); }

  async function renameScene(s) {
    const name = prompt(`New name of scene "${sceneLabel(s)}" (${s.id}):`, s.name || "");
    if (name === null || name.trim() === (s.name || "")) return;
    try {
      const scene = await (await api("/scenes/" + s.id, { method: "PATCH", body: JSON.stringify({ name }),
                                                           headers: { "Content-Type": "application/json" } })).json();
      showError("scenes-error", null);
      $("upload-status").textContent = `renamed to "${scene.name}"`;
      await loadScenes();
    } catch (err) { showError("scenes-error", err); }
  }

  async function deleteScene(s) {
    const label = sceneLabel(s);
    if (!confirm(`Delete scene "${label}" (${s.id})? Its checkpoints and videos are removed too.`)) return;
    const status = $("upload-status");
    try {
      await api("/scenes/" + s.id, { method: "DELETE" });
      showError("scenes-error", null);
      status.textContent = `deleted "${label}"`;
      for (const key of [...enhancedCache.keys()]) if (key.startsWith(s.id + ":")) enhancedCache.delete(key);
      if (viewsOf === s.id) { viewsOf = null; views = []; }
      const jobs = JSON.parse(sessionStorage.getItem(JOBS_ITEM) || "{}");
      if (jobShown && jobs[s.id] === jobShown) { stopWatching(); jobShown = null; $("job").hidden = true; }
      delete jobs[s.id];
      sessionStorage.setItem(JOBS_ITEM, JSON.stringify(jobs));
      await loadScenes();
    } catch (err) { showError("scenes-error", err); }
  }

  function upload(event) {
    event.preventDefault();
    const archive = $("upload-archive").files[0];
    if (!archive) return;
    const form = new FormData();
    form.append("archive", archive, archive.name);
    const name = $("upload-name").value.trim();
    if (name) form.append("name", name);
    const ckpt = $("upload-checkpoint").files[0];
    if (ckpt) form.append("checkpoint", ckpt, ckpt.name);
    const ply = $("upload-ply").files[0];   // a 3DGS .ply: the zip is its dataset, imported by a worker
    if (ply) form.append("ply", ply, ply.name);
    const xhr = new XMLHttpRequest();       // fetch cannot report upload progress
    const bar = $("upload-progress"), status = $("upload-status"), button = $("upload-submit");
    bar.value = 0; status.textContent = "uploading…"; button.disabled = true;
    showError("scenes-error", null);
    xhr.upload.addEventListener("progress", (e) => {
      if (e.lengthComputable) {
        bar.value = Math.round(100 * e.loaded / e.total);
        status.textContent = `${bar.value}% of ${(e.total / 1e6).toFixed(1)} MB`
          + (bar.value === 100 ? (ply ? ", checking the dataset…" : ", checking the scene…") : "");
      }
    });
    xhr.addEventListener("loadend", async () => {
      button.disabled = false;
      if (xhr.status === 201) {
        const scene = JSON.parse(xhr.responseText);
        bar.value = 100;
        status.textContent = `registered "${scene.name || scene.id}" (${scene.views} views)`;
        $("upload-form").reset();
        bar.value = 100;
        await loadScenes();
        selectScene(scene.id);
        return;
      }
      if (xhr.status === 202) {   // POST /scenes/import: a job renders the views, then the scene exists
        const job = JSON.parse(xhr.responseText);
        $("upload-form").reset();
        watchImport(job);
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
    xhr.open("POST", ply ? "/scenes/import" : "/scenes");
    const key = apiKey();
    if (key) xhr.setRequestHeader("Authorization", "Bearer " + key);
    xhr.send(form);
  }

  /** An import job (a dataset + .ply) until its scene exists: its progress in the upload's status. */
  function watchImport(job) {
    const status = $("upload-status"), label = job.request.name || job.scene_id.slice(0, 8);
    const poll = async () => {
      try {
        job = await getJSON("/jobs/" + job.id);
      } catch (err) { showError("scenes-error", err); setTimeout(poll, 3000); return; }
      if (job.state === "queued" || job.state === "running") {
        status.textContent = `importing "${label}": ` + (job.state === "queued" ? "waiting for a worker"
          : job.step ? `rendering view ${job.step} of ${job.total_steps}` : "loading the splats");
        setTimeout(poll, 1000);
        return;
      }
      if (job.state === "succeeded") {
        status.textContent = `imported "${label}" (${job.result.views} views)`;
        await loadScenes();
        selectScene(job.scene_id);
        return;
      }
      status.textContent = "import " + job.state;
      showError("scenes-error", new ApiError(0, job.error ? job.error.code : job.state,
                                             job.error ? job.error.message : "the import " + job.state));
    };
    poll();
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
      // The job this tab started, else the scene's newest fine-tuning job from the API (a reload
      // in a new tab, or a job started by another client, keeps its results on screen).
      const jobId = scene.active_job || rememberedJob(id) || await newestFinetuneJob(id);
      if ($("ft-scene").value !== id) return;   // another scene was picked meanwhile
      if (jobId) watchJob(jobId); else { stopWatching(); $("job").hidden = true; $("ft-cancel").disabled = true; }
    } catch (err) { showError("ft-error", err); }
  }

  async function newestFinetuneJob(sceneId) {
    const jobs = await getJSON(`/jobs?scene_id=${encodeURIComponent(sceneId)}&limit=50`);
    const job = jobs.items.find((j) => !(j.request || {}).kind);   // not a camera path, not an import
    return job ? job.id : null;
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
        else { jobTimer = null; await loadScenes(); showCheckpointDownload(); }
      } catch (err) {
        if (jobShown !== jobId) return;
        if (err.status === 404) {   // gone with its scene
          stopWatching(); jobShown = null; $("job").hidden = true; $("ft-cancel").disabled = true; return;
        }
        showError("ft-error", err); jobTimer = setTimeout(poll, 3000);
      }
    };
    poll();
  }

  /** What a job is doing, in words: the API's state and phase mapped for people. */
  function jobPhase(job) {
    if (job.state === "queued") return "waiting for a worker";
    if (job.state !== "running") return "–";   // finished: the state says how
    if (job.cancel_requested) return "stopping";
    if ((job.request || {}).kind === "path") return "enhancing frames";
    if (job.phase === "training") return "training";
    // Held-out views are measured before the first step and after the last one.
    if (job.phase === "evaluating") return job.step ? "measuring after" : "measuring before";
    return "loading the scene";
  }

  function showCheckpointDownload() {
    const s = sceneOf($("ft-scene").value), button = $("ft-download");
    const version = s ? s.active_version : 0;
    button.disabled = !version;
    button.textContent = version ? `Download checkpoint (${fmt.version(version)})` : "Download checkpoint";
    button.title = version ? "" : "this scene uses the server's default checkpoint (v0)";
  }

  async function downloadCheckpoint() {
    const s = sceneOf($("ft-scene").value);
    if (!s || !s.active_version) return;
    try {
      await download(`/scenes/${s.id}/checkpoints/${s.active_version}`,
                     `${fileSafe(sceneLabel(s))}-v${s.active_version}.safetensors`);
      showError("ft-error", null);
    } catch (err) { showError("ft-error", err); }
  }

  function renderJob(job) {
    $("job").hidden = false;
    const phase = jobPhase(job);
    $("job-phase").textContent = phase;
    $("job").dataset.phase = phase;
    $("job-id").textContent = job.id;
    $("job-state").textContent = job.state + (job.cancel_requested && job.state === "running" ? " (cancelling)" : "");
    $("job").dataset.state = job.state;
    $("job-step").textContent = job.step ? `${job.step}` + (job.total_steps ? ` of ${job.total_steps}` : "") : "–";
    $("job-loss").textContent = job.loss === null ? "–" : job.loss.toPrecision(4);
    $("job-eta").textContent = phase === "training" ? fmt.seconds(job.eta_s)
      : job.state === "queued" ? "waiting for a worker"
      : phase.startsWith("measuring") ? "measuring the held-out views" : "–";
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
  let views = [], viewsOf = null, compareAbort = null, shownView = null;
  const urls = { render: null, enhanced: null, photo: null };
  const RETRY_DELAYS_S = [0.5, 1, 2, 4];   // then every 4 s
  const MAX_ENHANCE_TRIES = 40;            // about 2.5 minutes of a busy server, then an error

  async function loadViews() {
    const id = $("cmp-scene").value;
    if (!id) return;
    if (viewsOf === id && views.length) return showView();
    if (compareAbort) compareAbort.abort();   // the previous scene's view is not drawn any more
    try {
      const items = (await getJSON(`/scenes/${id}/views?split=test`)).items;
      if ($("cmp-scene").value !== id) return;   // another scene was picked meanwhile
      views = items; viewsOf = id;
      $("cmp-view").replaceChildren(...views.map((v) => new Option(`${v.name} (#${v.index})`, String(v.index))));
      showError("cmp-error", null);
      if (!views.length) { $("cmp-status").textContent = "this scene has no test views"; return; }
      await showView();
    } catch (err) { showError("cmp-error", err); }
  }

  /** Resolves after ``s`` seconds; rejects at once when ``signal`` aborts. */
  function sleep(s, signal) {
    return new Promise((resolve, reject) => {
      if (signal.aborted) { reject(signal.reason); return; }
      const onAbort = () => { clearTimeout(timer); reject(signal.reason); };
      const timer = setTimeout(() => { signal.removeEventListener("abort", onAbort); resolve(); }, s * 1000);
      signal.addEventListener("abort", onAbort, { once: true });
    });
  }

  /** An object URL no element shows any more is released (a second later: an <img> may still
   *  be switching to its successor). */
  function retire(url) {
    if (!url) return;
    setTimeout(() => {
      const used = [...document.querySelectorAll("img, a, video")].some((e) => e.src === url || e.href === url);
      if (used || Object.values(urls).includes(url)) retire(url); else URL.revokeObjectURL(url);
    }, 1000);
  }

  /** Decode ``blob`` off-screen first; only a good image replaces what ``img-<kind>`` shows,
   *  so a failed or cancelled load never leaves a broken image behind. */
  async function showImage(kind, blob, signal) {
    const url = URL.createObjectURL(blob);
    try {
      const probe = new Image();
      probe.src = url;
      await probe.decode();
    } catch (_) {
      URL.revokeObjectURL(url);
      if (signal.aborted) throw signal.reason;
      throw new ApiError(0, "undecodable_image", `the ${kind} image could not be decoded`);
    }
    if (signal.aborted) { URL.revokeObjectURL(url); throw signal.reason; }
    const old = urls[kind];
    urls[kind] = url;
    $("img-" + kind).src = url;
    $("img-" + kind).closest("figure").hidden = false;
    retire(old);
  }

  function hideImage(kind) {
    const old = urls[kind];
    urls[kind] = null;
    $("img-" + kind).removeAttribute("src");
    $("img-" + kind).closest("figure").hidden = true;
    retire(old);
  }

  /** While the enhanced image of the shown view is not there: the old one stays, dimmed and
   *  labelled, and the stage shows the left image alone with the reason. */
  function setPending(text) {
    const pending = Boolean(text);
    $("compare").dataset.pending = String(pending);
    $("img-enhanced").classList.toggle("stale", pending);
    $("enhanced-caption").textContent = pending ? `enhanced: ${text}` : "enhanced";
    $("stage-note").textContent = text || "";
    $("stage-note").hidden = !pending;
    $("cmp-download").hidden = pending || !urls.enhanced;
    updateStage();
  }

  async function score(sceneId, index, blob, signal) {
    const form = new FormData();
    form.append("image", blob, "image.png");
    return (await api(`/scenes/${sceneId}/views/${index}/score`, { method: "POST", body: form, signal })).json();
  }

  /** POST /enhance; an over_capacity answer (all enhancement slots busy) is retried after
   *  0.5, 1, 2, then every 4 s, with a countdown in ``onBusy(secondsLeft, tryNumber)``. */
  async function postEnhance(form, signal, onBusy) {
    for (let attempt = 0; ; attempt++) {
      try {
        return await api("/enhance", { method: "POST", body: form, signal });
      } catch (err) {
        if (signal.aborted || !(err instanceof ApiError) || err.code !== "over_capacity"
            || attempt + 1 >= MAX_ENHANCE_TRIES) throw err;
        const wait = RETRY_DELAYS_S[Math.min(attempt, RETRY_DELAYS_S.length - 1)];
        for (let left = wait; left > 0; left -= 1) {
          onBusy(left, attempt + 2);
          await sleep(Math.min(1, left), signal);
        }
      }
    }
  }

  async function enhanced(sceneId, view, render, version, signal, onBusy) {
    const key = `${sceneId}:${view.index}:${version}`;
    if (enhancedCache.has(key)) return { ...enhancedCache.get(key), cached: true };
    const depth = await (await api(`/scenes/${sceneId}/views/${view.index}/depth`, { signal })).blob();
    const form = new FormData();
    form.append("scene_id", sceneId);
    form.append("render", render, "render.png");
    form.append("depth", depth, "depth.npy");
    form.append("camera", JSON.stringify(view.camera));
    const response = await postEnhance(form, signal, onBusy);
    const entry = {
      blob: await response.blob(),
      neighbours: (response.headers.get("X-Neighbours") || "").split(",").filter(Boolean),
      refined: (response.headers.get("X-Pose-Refined") || "").split(",").filter(Boolean),
      colour: (response.headers.get("X-Colour-Offset") || "").split(",").filter(Boolean).map(Number),
      trust: response.headers.has("X-Trust") ? Number(response.headers.get("X-Trust")) : NaN,
      agreement: response.headers.has("X-Neighbour-Agreement")
        ? Number(response.headers.get("X-Neighbour-Agreement")) : NaN,
      seconds: Number(response.headers.get("X-Enhance-Seconds")),
      version: response.headers.get("X-Checkpoint-Version"),
      note: response.headers.get("X-Enhance-Note"),
    };
    enhancedCache.set(`${sceneId}:${view.index}:${entry.version}`, entry);
    return { ...entry, cached: false };
  }

  const SCORE_IDS = ["m-render-psnr", "m-render-ssim", "m-enhanced-psnr", "m-enhanced-ssim"];

  /** Show the picked view. A newer pick aborts this one's requests and waits (AbortController):
   *  the newest view always wins, and nothing of an older one is drawn after it. */
  async function showView() {
    const sceneId = $("cmp-scene").value, index = Number($("cmp-view").value);
    const view = views.find((v) => v.index === index);
    if (!view) return;
    if (compareAbort) compareAbort.abort();
    const ctrl = new AbortController();
    compareAbort = ctrl;
    const { signal } = ctrl;
    const status = $("cmp-status"), cmp = $("compare");
    status.textContent = `loading ${view.name}…`;
    cmp.dataset.ready = "false";
    cmp.dataset.busy = "false";
    for (const id of SCORE_IDS) $(id).textContent = "…";
    try {
      const scene = await getJSON(`/scenes/${sceneId}`, signal);
      const [render, photo] = await Promise.all([
        api(`/scenes/${sceneId}/views/${index}/render`, { signal }).then((r) => r.blob()),
        view.has_photo ? api(`/scenes/${sceneId}/views/${index}/photo`, { signal }).then((r) => r.blob()) : null]);
      // The render and photo of the new view replace the old ones as soon as they decoded.
      await showImage("render", render, signal);
      if (photo) await showImage("photo", photo, signal); else hideImage("photo");
      shownView = view;
      const waiting = `enhancing ${view.name}…`;
      setPending(waiting);
      status.textContent = waiting;
      const out = await enhanced(sceneId, view, render, scene.active_version, signal, (left, attempt) => {
        const text = `busy, retrying in ${left < 1 ? left.toFixed(1) : Math.ceil(left)} s (try ${attempt})`;
        cmp.dataset.busy = "true";
        status.textContent = `${view.name}: all enhancement slots are busy; retrying in `
          + `${left < 1 ? left.toFixed(1) : Math.ceil(left)} s (try ${attempt})`;
        setPending(text);
      });
      cmp.dataset.busy = "false";
      await showImage("enhanced", out.blob, signal);
      const link = $("cmp-download");
      link.href = urls.enhanced;
      link.download = `${fileSafe(sceneLabel(sceneId))}-${fileSafe(view.name)}-enhanced-v${out.version}.png`;
      setPending(null);
      $("cmp-neighbours").textContent = out.neighbours
        .map((n) => (out.refined.includes(n) ? `${n} (pose refined)` : n)).join(", ") || "none";
      $("cmp-version").textContent = fmt.version(Number(out.version));
      $("cmp-colour").textContent = fmt.colour(out.colour);
      $("cmp-trust").textContent = fmt.trust(out.trust, out.agreement);
      $("cmp-seconds").textContent = out.cached ? `${out.seconds.toFixed(2)} s (cached result)` : `${out.seconds.toFixed(2)} s`;
      $("cmp-note").textContent = out.note || "–";
      status.textContent = `${view.name}: scoring…`;
      if (photo) {
        const [mr, me] = await Promise.all([score(sceneId, index, render, signal), score(sceneId, index, out.blob, signal)]);
        showScores({ render: mr, enhanced: me });
      } else for (const id of SCORE_IDS) $(id).textContent = "no photo";
      status.textContent = `${view.name}: ${view.width}×${view.height}`;
      showError("cmp-error", null);
      cmp.dataset.ready = "true";
    } catch (err) {
      if (signal.aborted) return;   // a newer view took over
      cmp.dataset.busy = "false";
      status.textContent = `${view.name}: not enhanced`;
      if (shownView === view) setPending(`not enhanced (${err.code})`);
      showError("cmp-error", err);
    }
  }

  /** The score endpoint's answer per image: PSNR and SSIM in their cells; any further metric
   *  it returns gets a column of its own (named after the field). */
  function showScores(byRow) {
    const table = $("cmp-metrics"), head = table.querySelector("thead tr");
    const known = new Set(["psnr", "ssim"]);
    for (const [row, m] of Object.entries(byRow)) {
      $(`m-${row}-psnr`).textContent = fmt.psnr(m.psnr);
      $(`m-${row}-ssim`).textContent = fmt.ssim(m.ssim);
      for (const [name, value] of Object.entries(m)) {
        if (known.has(name) || typeof value !== "number") continue;
        if (!head.querySelector(`[data-metric="${name}"]`)) {
          const th = document.createElement("th"); th.scope = "col"; th.dataset.metric = name;
          th.textContent = name.toUpperCase(); head.append(th);
          for (const r of table.querySelectorAll("tbody tr")) {
            const td = document.createElement("td"); td.id = `m-${r.dataset.row}-${name}`; td.textContent = "–"; r.append(td);
          }
        }
        const cellOf = $(`m-${row}-${name}`);
        if (cellOf) cellOf.textContent = Number(value).toFixed(4);
      }
    }
  }

  function updateStage() {
    const pending = $("compare").dataset.pending === "true";
    const pick = { render: urls.render, enhanced: pending ? null : urls.enhanced, photo: urls.photo };
    const left = pick[$("cmp-left").value], right = pick[$("cmp-right").value];
    if (left && $("cmp-before").src !== left) $("cmp-before").src = left;
    if (right && $("cmp-after").src !== right) $("cmp-after").src = right;
    // Nothing current for the right side (its enhancement is on its way): the left image alone.
    $("cmp-after").hidden = !right;
    $("cmp-handle").hidden = !right;
    applyZoom();
  }

  /** The stage's scale: "fit" fills the box (width or height, aspect kept), N× is N screen
   *  pixels per image pixel. Enlarged pixels stay sharp squares (pixelated). */
  function stageScale(view) {
    const choice = $("cmp-zoom").value;
    if (choice !== "fit") return Number(choice);
    const box = $("stage-scroll"), cs = getComputedStyle(box);
    const padX = parseFloat(cs.paddingLeft) + parseFloat(cs.paddingRight);
    const padY = parseFloat(cs.paddingTop) + parseFloat(cs.paddingBottom);
    const maxH = parseFloat(cs.maxHeight) || window.innerHeight * 0.7;
    const width = box.clientWidth - padX, height = maxH - padY;
    return Math.max(0.05, Math.min(width / view.width, height / view.height));
  }

  let lastZoom = null;
  function applyZoom() {
    const view = shownView || views.find((v) => v.index === Number($("cmp-view").value));
    if (!view) return;
    const scale = stageScale(view);
    const w = Math.floor(view.width * scale), h = Math.floor(view.height * scale);
    for (const id of ["cmp-before", "cmp-after"]) {
      $(id).style.width = w + "px";
      $(id).style.height = h + "px";
      $(id).style.imageRendering = scale >= 1 ? "pixelated" : "auto";
    }
    // Centred in its box while it fits (whole pixels: the stage's pixels stay on the screen's).
    const box = $("stage-scroll"), cs = getComputedStyle(box);
    const free = box.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight) - w;
    $("stage").style.marginLeft = free > 1 ? Math.floor(free / 2) + "px" : "0px";
    $("stage").dataset.scale = scale.toFixed(3);
    const key = `${$("cmp-zoom").value}:${view.width}x${view.height}`;
    if (key !== lastZoom) { lastZoom = key; keepDividerInView(true); } else keepDividerInView(false);
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

  /** Zoomed in, the stage is larger than its box: on a zoom change the box scrolls to centre
   *  the divider; when the user pans, the divider follows into the visible part (and its grip
   *  to the middle of it), so both images stay in sight at every zoom. */
  function keepDividerInView(centre) {
    const box = $("stage-scroll"), stage = $("stage"), width = stage.offsetWidth;
    if (!width) return;
    const x = stage.offsetLeft + width * divider / 100;
    if (centre) {
      box.scrollLeft = x - box.clientWidth / 2;
      box.scrollTop = (box.scrollHeight - box.clientHeight) / 2;
    } else {
      const margin = Math.min(24, box.clientWidth / 4);
      const lo = box.scrollLeft + margin, hi = box.scrollLeft + box.clientWidth - margin;
      if (x < lo || x > hi) setDivider(100 * ((x < lo ? lo : hi) - stage.offsetLeft) / width);
    }
    const top = Math.max(0, box.scrollTop - stage.offsetTop);
    const visible = Math.min(stage.offsetHeight - top, box.clientHeight);
    $("cmp-handle").style.setProperty("--grip", `${Math.round(top + visible / 2)}px`);
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
    $("stage-scroll").addEventListener("scroll", () => keepDividerInView(false), { passive: true });
    window.addEventListener("resize", () => { if (!$("compare").hidden) applyZoom(); });
    setDivider(50);
  }

  // ------------------------------------------------------------------ videos (camera-path jobs)
  let videoTimer = null;
  const pathJobs = new Map();

  function stopVideoPolling() { if (videoTimer) clearTimeout(videoTimer); videoTimer = null; }

  async function loadVideos() {
    stopVideoPolling();
    try {
      const jobs = (await getJSON("/jobs?limit=200")).items.filter((j) => (j.request || {}).kind === "path");
      renderVideos(jobs);
      showError("videos-error", null);
      if (jobs.some((j) => j.state === "queued" || j.state === "running") && location.hash === "#videos")
        videoTimer = setTimeout(loadVideos, 1000);
    } catch (err) { showError("videos-error", err); }
  }

  function renderVideos(jobs) {
    const body = $("videos-table").querySelector("tbody");
    body.replaceChildren();
    pathJobs.clear();
    for (const job of jobs) {
      pathJobs.set(job.id, job);
      const tr = document.createElement("tr");
      tr.dataset.job = job.id; tr.dataset.state = job.state;
      cell(tr, sceneBadge(job.scene_id), "Scene");
      const id = document.createElement("code"); id.className = "scene-id"; id.textContent = job.id;
      cell(tr, id, "Job");
      const state = document.createElement("div"); state.className = "video-state";
      const stateWord = document.createElement("span"); stateWord.className = "job-state";
      stateWord.textContent = job.state;
      const label = document.createElement("label");
      label.htmlFor = "vp-" + job.id; label.className = "sr-only"; label.textContent = `progress of job ${job.id}`;
      const bar = document.createElement("progress");
      bar.id = "vp-" + job.id; bar.max = 1; bar.value = job.progress;
      const words = document.createElement("span");
      // steps: one per frame, or one per frame and pass where the frames are blended both ways
      const frames = job.step ? ` · step ${job.step} of ${job.total_steps}` : "";
      const eta = job.state === "running" && job.eta_s !== null ? ` · ${fmt.seconds(job.eta_s)} left` : "";
      const doing = job.state === "queued" || job.state === "running" ? ` · ${jobPhase(job)}` : "";
      words.textContent = (job.error ? `: ${job.error.message} (${job.error.code})` : "") + doing + frames + eta;
      const line = document.createElement("span");
      line.append(stateWord, words);
      state.append(line, label, bar);
      cell(tr, state, "State");
      const flicker = ((job.result || {}).flicker) || {};
      cell(tr, Number.isFinite(flicker.render) && Number.isFinite(flicker.enhanced)
        ? `${flicker.render.toFixed(4)} → ${flicker.enhanced.toFixed(4)}`
          + (Number.isFinite(flicker.ratio) ? ` (×${flicker.ratio.toFixed(2)})` : "")
          + (Number.isFinite(flicker.ratio_sharpened)
            ? `; ×${flicker.ratio_sharpened.toFixed(2)} of the render sharpened alike` : "")
          + (flicker.neighbour_changes > 0 && Number.isFinite(flicker.ratio_changed)
            ? `; ×${flicker.ratio_changed.toFixed(2)} across the ${flicker.neighbour_changes} frame pairs`
              + " where the neighbour photos changed" : "")
        : "–", "Flicker");
      cell(tr, fmt.date(job.created_at), "Created");
      const actions = cell(tr, "", "Video");
      for (const [text, handler] of [["Play", () => playVideo(job)], ["Download", () => downloadVideo(job)]]) {
        const b = document.createElement("button");
        b.type = "button"; b.textContent = text; b.disabled = job.state !== "succeeded";
        b.setAttribute("aria-label", `${text} the video of job ${job.id.slice(0, 8)} (scene ${sceneLabel(job.scene_id)})`);
        b.addEventListener("click", handler);
        actions.append(b);
      }
      body.append(tr);
    }
    $("videos-empty").hidden = jobs.length > 0;
  }

  const videoName = (job) => `${fileSafe(sceneLabel(job.scene_id))}-path-${job.id.slice(0, 8)}.mp4`;

  async function playVideo(job) {
    const player = $("video-player");
    try {
      const blob = await (await api(`/jobs/${job.id}/result?what=video`)).blob();
      const url = URL.createObjectURL(blob), old = player.src;
      player.src = url;
      retire(old && old.startsWith("blob:") ? old : null);
      $("video-panel").hidden = false;
      $("video-caption").textContent = `Scene ${sceneLabel(job.scene_id)}, job ${job.id}: `
        + `${job.request.frames} frames, ${(blob.size / 1e6).toFixed(2)} MB`;
      $("video-panel").dataset.job = job.id;
      showError("videos-error", null);
      await player.play().catch(() => { /* autoplay refused: the controls are there */ });
    } catch (err) { showError("videos-error", err); }
  }

  async function downloadVideo(job) {
    try { await download(`/jobs/${job.id}/result?what=video`, videoName(job)); showError("videos-error", null); }
    catch (err) { showError("videos-error", err); }
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
    $("ft-scene").addEventListener("change", () => { $("cmp-scene").value = $("ft-scene").value; showCheckpointDownload(); showSceneJob(); });
    $("cmp-scene").addEventListener("change", () => { $("ft-scene").value = $("cmp-scene").value; loadViews(); });
    $("cmp-view").addEventListener("change", showView);
    $("cmp-left").addEventListener("change", () => { updateStage(); setDivider(divider); });
    $("cmp-right").addEventListener("change", () => { updateStage(); setDivider(divider); });
    $("cmp-zoom").addEventListener("change", applyZoom);
    $("ft-download").addEventListener("click", downloadCheckpoint);
    $("videos-refresh").addEventListener("click", loadVideos);
    $("video-player").addEventListener("error", () => {
      const e = $("video-player").error;
      showError("videos-error", new ApiError(0, "video_error", "this browser cannot play the MP4 (H.264): "
        + `${e ? e.message || "error " + e.code : "unknown error"}; download it instead`));
    });
    window.addEventListener("hashchange", route);
    reload();
  });
})();

// flatserve light-field viewer: no build step, no dependencies.
// Camera: eye on a sphere around the origin (yaw, pitch, distance), focal length.
// Each change POSTs the camera to /v1/fields/{name}/render and shows the PNG.
// While dragging, frames use 1 ray per pixel; at rest, 4 (the paper's 4x).
// ?camera=<URL-encoded JSON>: a captured frame's pose instead, {"nerf": {...}} or
// {"colmap": {...}} as the render body takes them (and optionally width, height,
// supersample, interpolant); without a size the frame is scaled to SIZE pixels on its
// longer side. That camera stays fixed (its intrinsics are the capture's, which the
// orbit cannot keep): drag, wheel and keys do nothing, and the page says so.
(function () {
  "use strict";
  const parts = location.pathname.split("/").filter(Boolean);
  const name = decodeURIComponent(parts[parts.length - 1] || "");
  // A server with API keys: the read-only key (FLATSERVE_READ_ONLY_KEY) as #key=... in the
  // URL, or typed into the form shown on a 401. The key is then kept for this tab only
  // (sessionStorage) and taken out of the address bar; the fragment never reaches a server.
  const hash = new URLSearchParams(location.hash.slice(1));
  const KEY_STORE = "flatserve-viewer-key";
  let apiKey = hash.get("key") || sessionStorage.getItem(KEY_STORE);
  if (hash.has("key")) {
    sessionStorage.setItem(KEY_STORE, apiKey);
    hash.delete("key");
    const rest = hash.toString();
    history.replaceState(null, "", location.pathname + location.search + (rest ? "#" + rest : ""));
  }
  const DEFAULT = { yaw: 0, pitch: 0, distance: 3, focal: 4 };
  // yaw turns all the way round (wrapped to (-180, 180]); pitch stops short of the poles
  // (the server takes |pitch| <= 89). A 360 degree field (an oriented atlas, the demo) has
  // every view; a one-chart field only those within ~45 degrees of its axis (the rest is
  // uncovered: the coverage line says so).
  const LIMITS = { pitch: 85, focalMin: 1.5, focalMax: 12 };
  const DEG_PER_PX = 0.15;                              // drag sensitivity
  const WHEEL_STEP = 1.1;                               // focal factor per wheel notch
  const SIZE = 250;                                     // frame resolution (shown at 2x)
  const RETRY_MS = 2000;                                // while the field is not there yet

  // the URL's pose (null: orbit), or why it cannot be used
  const POSE_KINDS = ["nerf", "colmap"];
  let pose = null, poseError = null;
  const cameraParam = new URLSearchParams(location.search).get("camera");
  if (cameraParam !== null) {
    try {
      const j = JSON.parse(cameraParam);
      if (!j || typeof j !== "object" || Array.isArray(j)) throw new Error("expected a JSON object");
      const kinds = POSE_KINDS.filter((k) => k in j);
      if (kinds.length !== 1) throw new Error('expected one of "nerf" or "colmap"');
      pose = j;
    } catch (err) {
      poseError = "camera in the URL (?camera=): " + err.message;
    }
  }
  const poseKind = pose ? POSE_KINDS.find((k) => k in pose) : null;

  // The render body of the URL's pose: its members as given, the frame scaled to SIZE
  // pixels on its longer side unless the JSON gives width or height.
  function poseBody(supersample) {
    const body = Object.assign({}, pose, { supersample: supersample, format: "png" });
    const f = pose[poseKind] || {};
    const w = poseKind === "nerf" ? f.w : f.width, h = poseKind === "nerf" ? f.h : f.height;
    if (!("width" in pose) && !("height" in pose) && Number.isInteger(w) && Number.isInteger(h) &&
        w > 0 && h > 0) {
      const scale = SIZE / Math.max(w, h);
      body.width = Math.max(1, Math.round(w * scale));
      body.height = Math.max(1, Math.round(h * scale));
    }
    return body;
  }

  const cam = Object.assign({}, DEFAULT);
  const img = document.getElementById("frame");
  const stage = document.getElementById("stage");
  const $ = (id) => document.getElementById(id);
  $("field-name").textContent = name;
  document.title = "flatserve viewer: " + name;

  let inFlight = false, pending = null, renders = 0, lastUrl = null, waitingForKey = false;

  $("key-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    apiKey = $("key").value.trim();
    sessionStorage.setItem(KEY_STORE, apiKey);
    $("key").value = "";
    $("key-form").hidden = true;
    $("status").textContent = "";
    waitingForKey = false;
    if (!inFlight) pump();
  });

  const wrapYaw = (y) => { y = ((y + 180) % 360 + 360) % 360 - 180; return y === -180 ? 180 : y; };
  const clampPitch = (p) => Math.max(-LIMITS.pitch, Math.min(LIMITS.pitch, p));

  function request(supersample) {
    if (pose) supersample = Number.isInteger(pose.supersample) ? pose.supersample : 4;
    pending = { supersample: supersample, cam: Object.assign({}, cam) };
    if (!inFlight && !waitingForKey) pump();
  }

  async function pump() {
    if (!pending) return;
    const job = pending; pending = null; inFlight = true;
    $("busy").hidden = false;
    const body = pose ? poseBody(job.supersample) : {
      orbit: { yaw: job.cam.yaw, pitch: job.cam.pitch, distance: job.cam.distance },
      focal: job.cam.focal, width: SIZE, height: SIZE, supersample: job.supersample, format: "png",
    };
    const headers = { "Content-Type": "application/json", "Accept": "image/png" };
    if (apiKey) headers["api-key"] = apiKey;
    const t0 = performance.now();
    try {
      const resp = await fetch("/v1/fields/" + encodeURIComponent(name) + "/render",
                               { method: "POST", headers: headers, body: JSON.stringify(body) });
      if (resp.status === 404 || resp.status === 503) {
        // the field may still be building (first start): keep the request and retry
        $("status").textContent = "waiting for field " + name + " (" + resp.status + ") ...";
        if (!pending) pending = job;
        await new Promise((r) => setTimeout(r, RETRY_MS));
        return;
      }
      if (resp.status === 401 || resp.status === 403) {
        // no key, or a wrong one: ask for the read-only key, then render this frame again
        $("status").textContent = (apiKey ? "the key was refused (" + resp.status + ")"
          : "this server needs an API key") + ": enter the read-only key (FLATSERVE_READ_ONLY_KEY)";
        $("key-form").hidden = false;
        $("key").focus();
        if (!pending) pending = job;
        waitingForKey = true;
        return;
      }
      if (!resp.ok) {
        let msg = resp.status + " " + resp.statusText;
        try { const j = await resp.json(); msg += ": " + JSON.stringify(j.detail); } catch (e) {}
        throw new Error(msg);
      }
      const blob = await resp.blob();
      const url = URL.createObjectURL(blob);
      await new Promise((ok, fail) => { img.onload = ok; img.onerror = fail; img.src = url; });
      if (lastUrl) URL.revokeObjectURL(lastUrl);
      lastUrl = url;
      const ms = performance.now() - t0;
      renders += 1;
      img.dataset.renders = String(renders);
      img.dataset.supersample = String(job.supersample);
      img.dataset.camera = poseKind || "orbit";          // the camera of the frame shown
      if (!pose) {
        img.dataset.yaw = String(job.cam.yaw);
        img.dataset.pitch = String(job.cam.pitch);
      } else {  // shown at its aspect ratio, the longer side filling the stage
        const big = Math.max(img.naturalWidth, img.naturalHeight);
        img.style.width = (500 * img.naturalWidth / big) + "px";
        img.style.height = (500 * img.naturalHeight / big) + "px";
      }
      const rays = img.naturalWidth * img.naturalHeight * job.supersample;
      $("render-time").textContent = ms.toFixed(0) + " ms round trip (" + rays.toLocaleString() +
        " rays, " + job.supersample + " per pixel)";
      $("server-timing").textContent = (resp.headers.get("Server-Timing") || "")
        .split(",").map((s) => s.trim().replace(";dur=", " ") + " ms").join(", ");
      const cov = parseFloat(resp.headers.get("X-Coverage") || "NaN");
      $("coverage").textContent = isNaN(cov) ? "–" : (100 * cov).toFixed(1) + " % of pixels inside the samples";
      $("camera").textContent = pose
        ? "the " + poseKind + " pose from the URL, " + img.naturalWidth + " x " + img.naturalHeight + " pixels (fixed)"
        : "yaw " + job.cam.yaw.toFixed(1) + "°, pitch " + job.cam.pitch.toFixed(1) +
          "°, distance " + job.cam.distance.toFixed(2) + ", focal " + job.cam.focal.toFixed(2);
      $("status").textContent = "";
    } catch (err) {
      $("status").textContent = "render failed: " + err.message;
    } finally {
      inFlight = false;
      $("busy").hidden = true;
      if (pending && !waitingForKey) pump();
    }
  }

  // drag: orbit the eye
  let drag = null;
  stage.addEventListener("pointerdown", (ev) => {
    if (pose) return;                                   // a fixed camera
    drag = { x: ev.clientX, y: ev.clientY, yaw: cam.yaw, pitch: cam.pitch };
    stage.setPointerCapture(ev.pointerId);
    stage.classList.add("dragging");
    ev.preventDefault();
  });
  stage.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    cam.yaw = wrapYaw(drag.yaw - (ev.clientX - drag.x) * DEG_PER_PX);
    cam.pitch = clampPitch(drag.pitch + (ev.clientY - drag.y) * DEG_PER_PX);
    request(1);
  });
  const endDrag = (ev) => {
    if (!drag) return;
    drag = null;
    stage.classList.remove("dragging");
    request(4);
  };
  stage.addEventListener("pointerup", endDrag);
  stage.addEventListener("pointercancel", endDrag);

  // wheel: focal length (zoom)
  let wheelTimer = null;
  stage.addEventListener("wheel", (ev) => {
    if (pose) return;
    ev.preventDefault();
    const f = ev.deltaY > 0 ? 1 / WHEEL_STEP : WHEEL_STEP;
    cam.focal = Math.max(LIMITS.focalMin, Math.min(LIMITS.focalMax, cam.focal * f));
    request(1);
    clearTimeout(wheelTimer);
    wheelTimer = setTimeout(() => request(4), 250);
  }, { passive: false });

  stage.addEventListener("dblclick", () => { if (!pose) { Object.assign(cam, DEFAULT); request(4); } });

  // keyboard: arrows orbit, +/- zoom
  stage.addEventListener("keydown", (ev) => {
    if (pose) return;
    const step = 5;
    if (ev.key === "ArrowLeft") cam.yaw = wrapYaw(cam.yaw + step);
    else if (ev.key === "ArrowRight") cam.yaw = wrapYaw(cam.yaw - step);
    else if (ev.key === "ArrowUp") cam.pitch = clampPitch(cam.pitch + step);
    else if (ev.key === "ArrowDown") cam.pitch = clampPitch(cam.pitch - step);
    else if (ev.key === "+" || ev.key === "=") cam.focal = Math.min(LIMITS.focalMax, cam.focal * WHEEL_STEP);
    else if (ev.key === "-") cam.focal = Math.max(LIMITS.focalMin, cam.focal / WHEEL_STEP);
    else return;
    ev.preventDefault();
    request(4);
  });

  if (poseError) {
    $("status").textContent = poseError;               // nothing rendered: the URL asked for a pose
    $("camera").textContent = "none (the URL's camera could not be read)";
  } else {
    if (pose) {
      $("hint").hidden = true;
      $("pose-note").hidden = false;
      $("pose-note").textContent = "Camera fixed: the " + poseKind + " pose given in the URL (?camera=), " +
        "with the capture's own intrinsics; drag and wheel do nothing. Open the page without " +
        "?camera= to orbit.";
      stage.style.cursor = "default";
    }
    request(4);
  }
})();

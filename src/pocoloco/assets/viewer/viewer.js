// pocoloco point-cloud viewer: plain WebGL1, no dependencies (part of pocoloco, Apache-2.0).
// Reads the JSON in <script id="pocoloco-data"> (written by pocoloco/viewer.py), draws one
// cloud at a time as round point sprites with a perspective orbit camera (Z up).
(function () {
  "use strict";
  var data = JSON.parse(document.getElementById("pocoloco-data").textContent);
  var state = {
    ready: false, numClouds: data.clouds.length, numPointsShown: 0, current: 0,
    coveredPixels: 0, colorMode: "", error: null, frames: 0
  };
  window.pocolocoViewer = state;
  var statusEl = document.getElementById("status");

  function publish() {
    statusEl.setAttribute("data-ready", state.ready ? "1" : "0");
    statusEl.setAttribute("data-num-clouds", String(state.numClouds));
    statusEl.setAttribute("data-num-points-shown", String(state.numPointsShown));
    statusEl.setAttribute("data-current", String(state.current));
    statusEl.setAttribute("data-covered-pixels", String(state.coveredPixels));
    statusEl.setAttribute("data-color-mode", state.colorMode);
    var c = data.clouds[state.current];
    statusEl.textContent = state.error ? state.error :
      (state.numPointsShown + " of " + c.total + " points \u00b7 cloud " + (state.current + 1) + "/" + state.numClouds);
  }

  function fail(msg) {
    state.error = msg;
    var d = document.createElement("div");
    d.id = "error";
    d.textContent = msg;
    document.body.appendChild(d);
    publish();
  }

  // ------------------------------------------------------------------ decoding
  function bytes(b64) {
    var s = atob(b64), a = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) a[i] = s.charCodeAt(i);
    return a;
  }
  var clouds = data.clouds.map(function (c) {
    var out = { name: c.name, n: c.n, total: c.total, pos: new Float32Array(bytes(c.pos).buffer) };
    if (c.nrm) {
      var q = bytes(c.nrm), nrm = new Float32Array(q.length);
      for (var i = 0; i < q.length; i++) nrm[i] = q[i] / 127.5 - 1.0;
      out.nrm = nrm;
    }
    if (c.lab) out.lab = bytes(c.lab);
    return out;
  });
  var hasNormals = clouds.every(function (c) { return !!c.nrm; });
  var hasLabels = clouds.every(function (c) { return !!c.lab; });

  // ------------------------------------------------------------------ colours
  var LABEL_COLORS = [[0.87, 0.72, 0.62], [0.25, 0.47, 0.82], [0.95, 0.6, 0.2]];  // as pocoloco.render
  var VIRIDIS = [[0.267, 0.005, 0.329], [0.230, 0.322, 0.546], [0.128, 0.567, 0.551],
                 [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]];
  function viridis(t) {
    t = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
    var i = Math.min(Math.floor(t), VIRIDIS.length - 2), f = t - i, a = VIRIDIS[i], b = VIRIDIS[i + 1];
    return [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])];
  }
  function colors(c, mode) {
    var col = new Float32Array(c.n * 3), i, k;
    if (mode === "normal") {
      for (i = 0; i < c.n * 3; i++) col[i] = 0.5 * (c.nrm[i] + 1.0);
    } else if (mode === "label") {
      for (i = 0; i < c.n; i++) {
        var rgb = LABEL_COLORS[Math.min(c.lab[i], LABEL_COLORS.length - 1)];
        for (k = 0; k < 3; k++) col[3 * i + k] = rgb[k];
      }
    } else {  // height
      var z0 = data.zrange[0], dz = Math.max(data.zrange[1] - z0, 1e-9);
      for (i = 0; i < c.n; i++) {
        var v = viridis((c.pos[3 * i + 2] - z0) / dz);
        for (k = 0; k < 3; k++) col[3 * i + k] = v[k];
      }
    }
    return col;
  }

  // ------------------------------------------------------------------ matrices (column-major)
  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { var l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function lookAt(eye, target, up) {
    var z = norm(sub(eye, target)), x = norm(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
            -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function mul(a, b) {
    var o = new Array(16);
    for (var c = 0; c < 4; c++) for (var r = 0; r < 4; r++) {
      var s = 0;
      for (var k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      o[c * 4 + r] = s;
    }
    return o;
  }

  // ------------------------------------------------------------------ WebGL
  var canvas = document.getElementById("view");
  var gl = canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true }) ||
           canvas.getContext("experimental-webgl", { preserveDrawingBuffer: true });
  if (!gl) { fail("WebGL is not available in this browser"); return; }
  var VS = [
    "attribute vec3 aPos; attribute vec3 aCol; attribute vec3 aNrm;",
    "uniform mat4 uMVP; uniform vec3 uEye; uniform float uSize; uniform float uProj; uniform float uShade;",
    "varying vec3 vCol;",
    "void main() {",
    "  vec4 p = uMVP * vec4(aPos, 1.0);",
    "  float light = 1.0;",
    "  if (uShade > 0.5) {",  // headlight Lambert; cull points facing away (hidden in a solid surface)
    "    float f = dot(normalize(aNrm + vec3(1e-6)), normalize(uEye - aPos));",
    "    if (f < -0.15) p = vec4(2.0, 2.0, 2.0, 1.0);",
    "    light = 0.3 + 0.7 * pow(max(f, 0.0), 0.7);",
    "  }",
    "  gl_Position = p;",
    "  gl_PointSize = clamp(uSize * uProj / p.w, 1.5, 64.0);",
    "  vCol = aCol * light;",
    "}"].join("\n");
  var FS = [
    "precision mediump float; varying vec3 vCol;",
    "void main() { vec2 d = gl_PointCoord - 0.5; if (dot(d, d) > 0.25) discard; gl_FragColor = vec4(vCol, 1.0); }"
  ].join("\n");
  function shader(type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  var prog;
  try {
    prog = gl.createProgram();
    gl.attachShader(prog, shader(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail("WebGL shader error: " + e.message); return; }
  gl.useProgram(prog);
  var loc = {
    pos: gl.getAttribLocation(prog, "aPos"), col: gl.getAttribLocation(prog, "aCol"),
    nrm: gl.getAttribLocation(prog, "aNrm"), mvp: gl.getUniformLocation(prog, "uMVP"),
    eye: gl.getUniformLocation(prog, "uEye"), size: gl.getUniformLocation(prog, "uSize"),
    proj: gl.getUniformLocation(prog, "uProj"), shade: gl.getUniformLocation(prog, "uShade")
  };
  function buffer(arr) {
    var b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, arr, gl.STATIC_DRAW);
    return b;
  }
  clouds.forEach(function (c) {
    c.posBuf = buffer(c.pos);
    if (c.nrm) c.nrmBuf = buffer(c.nrm);
    c.colBuf = {};
  });
  gl.enable(gl.DEPTH_TEST);
  gl.clearColor(0.957, 0.957, 0.949, 1.0);  // #f4f4f2, as the page

  // ------------------------------------------------------------------ camera and drawing
  var FOV = 40 * Math.PI / 180;
  var cam = {};
  function resetCamera() {
    cam.az = 0; cam.el = 0.1; cam.target = data.center.slice();
    cam.dist = 0.95 * data.radius / Math.sin(FOV / 2);
  }
  resetCamera();
  var sizeScale = 1.0;
  var modes = (hasNormals ? ["normal"] : []).concat(hasLabels ? ["label"] : []).concat(["height"]);
  state.colorMode = modes[0];
  function eyePos() {
    var ce = Math.cos(cam.el);
    return [cam.target[0] + cam.dist * ce * Math.sin(cam.az), cam.target[1] - cam.dist * ce * Math.cos(cam.az),
            cam.target[2] + cam.dist * Math.sin(cam.el)];
  }
  function countCovered() {
    var w = gl.drawingBufferWidth, h = gl.drawingBufferHeight, px = new Uint8Array(w * h * 4), n = 0;
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    for (var i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 244) + Math.abs(px[i + 1] - 244) + Math.abs(px[i + 2] - 242) > 24) n++;
    }
    return n;
  }
  var pending = false;
  function draw() {
    pending = false;
    var dpr = window.devicePixelRatio || 1;
    var w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, w, h);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    var c = clouds[state.current], eye = eyePos();
    var near = Math.max(cam.dist - 3 * data.radius, cam.dist * 0.01), far = cam.dist + 3 * data.radius;
    var mvp = mul(perspective(FOV, w / h, near, far), lookAt(eye, cam.target, [0, 0, 1]));
    gl.uniformMatrix4fv(loc.mvp, false, new Float32Array(mvp));
    gl.uniform3fv(loc.eye, new Float32Array(eye));
    // world-space splat diameter from the mean spacing of n samples on a body-sized surface
    gl.uniform1f(loc.size, sizeScale * 3.0 * data.radius / Math.sqrt(Math.max(c.n, 1)));
    gl.uniform1f(loc.proj, h / (2 * Math.tan(FOV / 2)));
    if (!c.colBuf[state.colorMode]) c.colBuf[state.colorMode] = buffer(colors(c, state.colorMode));
    gl.bindBuffer(gl.ARRAY_BUFFER, c.posBuf);
    gl.enableVertexAttribArray(loc.pos);
    gl.vertexAttribPointer(loc.pos, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, c.colBuf[state.colorMode]);
    gl.enableVertexAttribArray(loc.col);
    gl.vertexAttribPointer(loc.col, 3, gl.FLOAT, false, 0, 0);
    if (c.nrmBuf && loc.nrm >= 0) {
      gl.bindBuffer(gl.ARRAY_BUFFER, c.nrmBuf);
      gl.enableVertexAttribArray(loc.nrm);
      gl.vertexAttribPointer(loc.nrm, 3, gl.FLOAT, false, 0, 0);
    } else if (loc.nrm >= 0) {
      gl.disableVertexAttribArray(loc.nrm);
      gl.vertexAttrib3f(loc.nrm, 0, 0, 1);
    }
    gl.uniform1f(loc.shade, c.nrmBuf ? 1.0 : 0.0);
    gl.drawArrays(gl.POINTS, 0, c.n);
    state.numPointsShown = c.n;
    state.frames++;
    if (!state.ready || state.frames % 30 === 0) state.coveredPixels = countCovered();
    state.ready = true;
    publish();
  }
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(draw); } }

  // ------------------------------------------------------------------ controls
  var nameEl = document.getElementById("name"), slider = document.getElementById("slider");
  var playBtn = document.getElementById("play"), cloudBtns = [];
  function select(i) {
    state.current = ((i % clouds.length) + clouds.length) % clouds.length;
    nameEl.textContent = clouds[state.current].name;
    slider.value = String(state.current);
    cloudBtns.forEach(function (b, k) { b.className = k === state.current ? "on" : ""; });
    redraw();
  }
  if (clouds.length <= 24 && !data.animation) {
    var box = document.getElementById("clouds");
    clouds.forEach(function (c, k) {
      var b = document.createElement("button");
      b.textContent = String(k);
      b.title = c.name + " (" + c.total + " points)";
      b.onclick = function () { stop(); select(k); };
      box.appendChild(b);
      cloudBtns.push(b);
    });
  }
  if (clouds.length > 1) {
    slider.max = String(clouds.length - 1);
    slider.oninput = function () { stop(); select(parseInt(slider.value, 10)); };
  } else {
    document.getElementById("anim").style.display = "none";
  }
  var timer = null;
  function stop() { if (timer) { clearInterval(timer); timer = null; playBtn.innerHTML = "&#9654;"; } }
  function play() {
    if (timer) { stop(); return; }
    playBtn.innerHTML = "&#10074;&#10074;";
    timer = setInterval(function () { select(state.current + 1); }, 1000 / data.fps);
  }
  playBtn.onclick = play;
  var colorSel = document.getElementById("color");
  modes.forEach(function (m) {
    var o = document.createElement("option");
    o.value = m; o.textContent = m;
    colorSel.appendChild(o);
  });
  colorSel.onchange = function () { state.colorMode = colorSel.value; redraw(); };
  document.getElementById("size").oninput = function (e) { sizeScale = parseFloat(e.target.value); redraw(); };

  var drag = null;
  canvas.addEventListener("contextmenu", function (e) { e.preventDefault(); });
  canvas.addEventListener("pointerdown", function (e) {
    drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", function () { drag = null; });
  canvas.addEventListener("pointermove", function (e) {
    if (!drag) return;
    var dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      var s = 2 * cam.dist * Math.tan(FOV / 2) / Math.max(canvas.clientHeight, 1);
      var right = [Math.cos(cam.az), Math.sin(cam.az), 0];
      var fwd = norm(sub(cam.target, eyePos())), up = cross(right, fwd);
      for (var k = 0; k < 3; k++) cam.target[k] += s * (-dx * right[k] + dy * up[k]);
    } else {
      cam.az -= dx * 0.008;
      cam.el = Math.min(Math.max(cam.el + dy * 0.008, -1.55), 1.55);
    }
    redraw();
  });
  canvas.addEventListener("wheel", function (e) {
    e.preventDefault();
    cam.dist *= Math.exp(0.0015 * e.deltaY);
    redraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { resetCamera(); redraw(); });
  window.addEventListener("resize", redraw);
  window.addEventListener("keydown", function (e) {
    if (e.target && e.target.tagName === "SELECT") return;
    if (e.key === "ArrowRight") { stop(); select(state.current + 1); }
    else if (e.key === "ArrowLeft") { stop(); select(state.current - 1); }
    else if (e.key === " ") { e.preventDefault(); play(); }
    else if (e.key === "c") {
      state.colorMode = modes[(modes.indexOf(state.colorMode) + 1) % modes.length];
      colorSel.value = state.colorMode;
      redraw();
    } else if (e.key === "+" || e.key === "=") { sizeScale *= 1.2; redraw(); }
    else if (e.key === "-") { sizeScale /= 1.2; redraw(); }
  });
  // start-up options in the URL hash, e.g. viewer.html#cloud=2&color=label&az=30&el=10 (degrees)
  var opts = {};
  location.hash.replace(/^#/, "").split("&").forEach(function (kv) {
    var p = kv.split("=");
    if (p.length === 2) opts[decodeURIComponent(p[0])] = decodeURIComponent(p[1]);
  });
  if (modes.indexOf(opts.color) >= 0) { state.colorMode = opts.color; colorSel.value = opts.color; }
  if (isFinite(parseFloat(opts.az))) cam.az = parseFloat(opts.az) * Math.PI / 180;
  if (isFinite(parseFloat(opts.el))) cam.el = Math.min(Math.max(parseFloat(opts.el), -89), 89) * Math.PI / 180;
  select(isFinite(parseInt(opts.cloud, 10)) ? parseInt(opts.cloud, 10) : 0);
  draw();  // the first frame now, not on the next animation frame (headless browsers may not tick)
})();

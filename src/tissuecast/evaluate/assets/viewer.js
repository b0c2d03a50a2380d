// tissuecast report: interactive 3D view of true and predicted deformation (WebGL 1, no library).
// Reads window.TISSUECAST_VIEW (viewer_data.js, written next to this file by tissuecast.evaluate.viewer):
// the outer surface (undeformed LPS mm), markers, targets and per sample the true (FEM) and
// predicted displacements of its vertices. Left: the true deformed surface coloured by displacement;
// right: the predicted surface coloured by its error. Drag to rotate, wheel to zoom, double-click to reset.
// Sets data-drawn="true" on #tc-viewer after the first frame (the report's browser test reads it).
(function () {
  "use strict";
  // ten stops of matplotlib's viridis and inferno colour maps (van der Walt, Smith, Firing; released under CC0)
  var VIRIDIS = ["#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"];
  var INFERNO = ["#000004", "#1b0c41", "#4a0c6b", "#781c6d", "#a52c60", "#cf4446", "#ed6925", "#fb9b06", "#f7d13d", "#fcffa4"];

  function rgb(hex) { return [1, 3, 5].map(function (i) { return parseInt(hex.substr(i, 2), 16) / 255; }); }
  function lut(stops) { return stops.map(rgb); }
  var MAPS = {displacement: lut(VIRIDIS), error: lut(INFERNO)};

  function colour(map, t) {
    t = Math.min(1, Math.max(0, t)) * (map.length - 1);
    var i = Math.min(map.length - 2, Math.floor(t)), f = t - i, a = map[i], b = map[i + 1];
    return [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2])];
  }

  // ---- small matrix helpers (column-major, as WebGL wants)
  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { var l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function lookAt(eye, centre, up) {
    var z = norm(sub(eye, centre)), x = norm(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }

  var VS = "attribute vec3 aPos; attribute vec3 aNrm; attribute vec3 aCol;" +
    "uniform mat4 uView; uniform mat4 uProj; uniform mat3 uRot; uniform float uSize;" +
    "varying vec3 vCol; varying float vShade;" +
    "void main() { gl_Position = uProj * uView * vec4(aPos, 1.0); vec3 n = uRot * aNrm;" +
    " vShade = 0.35 + 0.65 * abs(normalize(n + vec3(0.0, 0.0, 1e-6)).z); vCol = aCol; gl_PointSize = uSize; }";
  var FS = "precision mediump float; varying vec3 vCol; varying float vShade;" +
    "uniform float uLit; uniform float uAlpha; uniform float uRound;" +
    "void main() { if (uRound > 0.5) { vec2 d = gl_PointCoord - vec2(0.5); if (dot(d, d) > 0.25) discard; }" +
    " gl_FragColor = vec4(vCol * mix(1.0, vShade, uLit), uAlpha); }";

  function shader(gl, type, text) {
    var s = gl.createShader(type);
    gl.shaderSource(s, text);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
    return s;
  }

  function program(gl) {
    var p = gl.createProgram();
    gl.attachShader(p, shader(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(p, shader(gl, gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error("program: " + gl.getProgramInfoLog(p));
    var loc = {};
    ["aPos", "aNrm", "aCol"].forEach(function (n) { loc[n] = gl.getAttribLocation(p, n); });
    ["uView", "uProj", "uRot", "uSize", "uLit", "uAlpha", "uRound"].forEach(function (n) { loc[n] = gl.getUniformLocation(p, n); });
    return {id: p, loc: loc};
  }

  // positions (n*3) + displacement (n*3) * scale -> deformed positions
  function deformed(points, u, scale) {
    var out = new Float32Array(points.length);
    for (var i = 0; i < points.length; i++) out[i] = points[i] + scale * (u ? u[i] : 0);
    return out;
  }

  function vertexNormals(pos, tri) {
    var n = new Float32Array(pos.length);
    for (var t = 0; t < tri.length; t += 3) {
      var a = tri[t] * 3, b = tri[t + 1] * 3, c = tri[t + 2] * 3;
      var e1 = [pos[b] - pos[a], pos[b + 1] - pos[a + 1], pos[b + 2] - pos[a + 2]];
      var e2 = [pos[c] - pos[a], pos[c + 1] - pos[a + 1], pos[c + 2] - pos[a + 2]];
      var f = cross(e1, e2);
      [a, b, c].forEach(function (v) { n[v] += f[0]; n[v + 1] += f[1]; n[v + 2] += f[2]; });
    }
    return n;
  }

  // per-vertex arrays -> one vertex per triangle corner (drawArrays: no index-size limit)
  function expand(tri, arr) {
    var out = new Float32Array(tri.length * 3);
    for (var k = 0; k < tri.length; k++) {
      var v = tri[k] * 3;
      out[3 * k] = arr[v]; out[3 * k + 1] = arr[v + 1]; out[3 * k + 2] = arr[v + 2];
    }
    return out;
  }

  function magnitudes(a, b) {
    var m = new Float32Array(a.length / 3), top = 0;
    for (var i = 0; i < m.length; i++) {
      var dx = a[3 * i] - (b ? b[3 * i] : 0), dy = a[3 * i + 1] - (b ? b[3 * i + 1] : 0), dz = a[3 * i + 2] - (b ? b[3 * i + 2] : 0);
      m[i] = Math.sqrt(dx * dx + dy * dy + dz * dz);
      top = Math.max(top, m[i]);
    }
    return {values: m, max: top};
  }

  function colours(values, top, map) {
    var c = new Float32Array(values.length * 3);
    for (var i = 0; i < values.length; i++) {
      var rgbv = colour(map, top > 0 ? values[i] / top : 0);
      c[3 * i] = rgbv[0]; c[3 * i + 1] = rgbv[1]; c[3 * i + 2] = rgbv[2];
    }
    return c;
  }

  function edges(tri) {
    var seen = {}, out = [];
    for (var t = 0; t < tri.length; t += 3) {
      for (var k = 0; k < 3; k++) {
        var a = tri[t + k], b = tri[t + (k + 1) % 3], key = a < b ? a + "," + b : b + "," + a;
        if (!seen[key]) { seen[key] = 1; out.push(a, b); }
      }
    }
    return out;
  }

  function fmt(v) { return (v < 10 ? v.toFixed(2) : v.toFixed(1)) + " mm"; }

  function Viewer(root, data) {
    this.root = root;
    this.data = data;
    this.canvas = root.querySelector("canvas");
    var gl = this.canvas.getContext("webgl", {antialias: true, preserveDrawingBuffer: true});
    if (!gl) throw new Error("WebGL is not available in this browser");
    this.gl = gl;
    this.prog = program(gl);
    this.buffers = {};
    this.edgeIndex = edges(data.triangles);
    var p = data.points, lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (var i = 0; i < p.length; i++) { lo[i % 3] = Math.min(lo[i % 3], p[i]); hi[i % 3] = Math.max(hi[i % 3], p[i]); }
    this.centre = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2];
    this.radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2;
    this.reset();
    this.controls();
    this.update();
  }

  Viewer.prototype.reset = function () { this.yaw = 0.5; this.pitch = 0.25; this.distance = 3.0 * this.radius; };

  Viewer.prototype.q = function (name) { return this.root.querySelector("[data-control=" + name + "]"); };

  Viewer.prototype.controls = function () {
    var self = this, c = this.canvas, drag = null;
    var sample = this.q("sample"), method = this.q("method");
    this.data.samples.forEach(function (s, i) { sample.add(new Option(s.label, String(i))); });
    this.data.methods.forEach(function (m) { method.add(new Option(self.data.method_labels[m], m)); });
    ["sample", "method", "scale", "outline", "inside"].forEach(function (n) {
      self.q(n).addEventListener(n === "scale" ? "input" : "change", function () { self.update(); });
    });
    c.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY]; c.setPointerCapture(e.pointerId); });
    c.addEventListener("pointerup", function () { drag = null; });
    c.addEventListener("pointermove", function (e) {
      if (!drag) return;
      self.yaw -= (e.clientX - drag[0]) * 0.01;
      self.pitch = Math.max(-1.5, Math.min(1.5, self.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      self.request();
    });
    c.addEventListener("wheel", function (e) { e.preventDefault(); self.distance *= Math.exp(e.deltaY * 0.001); self.request(); },
      {passive: false});
    c.addEventListener("dblclick", function () { self.reset(); self.request(); });
    window.addEventListener("resize", function () { self.request(); });
  };

  Viewer.prototype.buffer = function (name, array) {
    var gl = this.gl, b = this.buffers[name] || (this.buffers[name] = gl.createBuffer());
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, array, gl.DYNAMIC_DRAW);
    return {buffer: b, count: array.length / 3};
  };

  // one panel's geometry: surface (expanded), outline, marker and target points
  Viewer.prototype.panel = function (key, u, colourValues, top, map, markers, targets) {
    var d = this.data, scale = parseFloat(this.q("scale").value);
    var pos = deformed(d.points, u, scale);
    var col = colours(colourValues, top, map);
    var nrm = vertexNormals(pos, d.triangles);
    var out = {
      surface: [this.buffer(key + "p", expand(d.triangles, pos)), this.buffer(key + "n", expand(d.triangles, nrm)),
        this.buffer(key + "c", expand(d.triangles, col))]
    };
    var base = deformed(d.points, null, 0);
    out.outline = [this.buffer(key + "op", expand(this.edgeIndex, base))];
    out.markers = [this.buffer(key + "mp", deformed(d.markers, markers, scale))];
    out.targets = [this.buffer(key + "tp", deformed(d.targets, targets, scale))];
    return out;
  };

  Viewer.prototype.update = function () {
    var d = this.data, s = d.samples[parseInt(this.q("sample").value || "0", 10)], m = this.q("method").value || d.methods[0];
    var pred = s.methods[m], truth = s.true;
    var disp = magnitudes(truth, null), err = magnitudes(pred, truth);
    this.panels = [
      this.panel("L", truth, disp.values, disp.max, MAPS.displacement, s.markers, s.targets_true),
      this.panel("R", pred, err.values, err.max, MAPS.error, s.markers, s.targets[m])
    ];
    this.q("scale-value").textContent = "×" + parseFloat(this.q("scale").value).toFixed(1);
    this.q("title-left").textContent = "true (FEM): displacement, largest " + fmt(disp.max);
    this.q("title-right").textContent = d.method_labels[m] + ": predicted, error up to " + fmt(err.max);
    this.q("max-left").textContent = fmt(disp.max);
    this.q("max-right").textContent = fmt(err.max);
    this.request();
  };

  Viewer.prototype.request = function () {
    var self = this;
    if (this.pending) return;
    this.pending = true;
    window.requestAnimationFrame(function () { self.pending = false; self.draw(); });
  };

  Viewer.prototype.attrib = function (name, buffer) {
    var gl = this.gl, loc = this.prog.loc[name];
    if (loc < 0) return;
    if (!buffer) { gl.disableVertexAttribArray(loc); gl.vertexAttrib3f(loc, 0, 0, 1); return; }
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer.buffer);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
  };

  // parts: [positions, normals?, colours?] buffers; rgbConst: one colour when there are no colours
  Viewer.prototype.drawParts = function (parts, mode, lit, alpha, size, rgbConst) {
    var gl = this.gl, L = this.prog.loc;
    rgbConst = rgbConst || [0.5, 0.5, 0.5];
    this.attrib("aPos", parts[0]);
    this.attrib("aNrm", parts[1] || null);
    if (parts[2]) this.attrib("aCol", parts[2]);
    else { gl.disableVertexAttribArray(L.aCol); gl.vertexAttrib3f(L.aCol, rgbConst[0], rgbConst[1], rgbConst[2]); }
    gl.uniform1f(L.uLit, lit);
    gl.uniform1f(L.uAlpha, alpha);
    gl.uniform1f(L.uSize, size);
    gl.uniform1f(L.uRound, mode === gl.POINTS ? 1 : 0);
    gl.drawArrays(mode, 0, parts[0].count);
  };

  Viewer.prototype.draw = function () {
    var gl = this.gl, c = this.canvas, dpr = window.devicePixelRatio || 1, L = this.prog.loc;
    var w = Math.max(2, Math.round(c.clientWidth * dpr)), h = Math.max(2, Math.round(c.clientHeight * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    var half = Math.floor(w / 2);
    var cp = Math.cos(this.pitch), eye = [
      this.centre[0] + this.distance * cp * Math.sin(this.yaw),
      this.centre[1] - this.distance * cp * Math.cos(this.yaw),
      this.centre[2] + this.distance * Math.sin(this.pitch)];
    var view = lookAt(eye, this.centre, [0, 0, 1]);
    var rot = [view[0], view[1], view[2], view[4], view[5], view[6], view[8], view[9], view[10]];
    var proj = perspective(0.6, half / h, this.distance / 20, this.distance * 4);
    var outline = this.q("outline").checked, inside = this.q("inside").checked;
    gl.useProgram(this.prog.id);
    gl.uniformMatrix4fv(L.uView, false, new Float32Array(view));
    gl.uniformMatrix4fv(L.uProj, false, new Float32Array(proj));
    gl.uniformMatrix3fv(L.uRot, false, new Float32Array(rot));
    gl.enable(gl.SCISSOR_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    for (var k = 0; k < 2; k++) {
      var p = this.panels[k];
      gl.viewport(k * half, 0, half, h);
      gl.scissor(k * half, 0, half, h);
      gl.clearColor(1, 1, 1, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      gl.enable(gl.DEPTH_TEST);
      if (inside) {  // targets first, seen through a see-through surface
        this.drawParts(p.targets, gl.POINTS, 0, 1, 9 * dpr, [0.1, 0.75, 1.0]);
        gl.depthMask(false);
        this.drawParts(p.surface, gl.TRIANGLES, 1, 0.35, 1);
        gl.depthMask(true);
      } else {
        this.drawParts(p.surface, gl.TRIANGLES, 1, 1, 1);
      }
      if (outline) this.drawParts(p.outline, gl.LINES, 0, 0.25, 1, [0.3, 0.3, 0.3]);
      gl.disable(gl.DEPTH_TEST);
      this.drawParts(p.markers, gl.POINTS, 0, 1, 8 * dpr, [0.9, 0.1, 0.1]);
    }
    if (this.root.getAttribute("data-drawn") !== "true") this.root.setAttribute("data-drawn", "true");
  };

  function start() {
    var root = document.getElementById("tc-viewer");
    if (!root) return;
    try {
      if (!window.TISSUECAST_VIEW) throw new Error("viewer_data.js did not load");
      root.viewer = new Viewer(root, window.TISSUECAST_VIEW);
    } catch (e) {
      root.setAttribute("data-drawn", "error");
      ["tc-controls", "tc-panels", "tc-canvas"].forEach(function (name) {  // no empty frame, no dead controls
        var el = root.querySelector("." + name);
        if (el) el.style.display = "none";  // not `hidden`: the stylesheet sets their display
      });
      var renders = document.getElementById("tc-renders");
      if (renders) renders.open = true;
      var box = root.querySelector(".tc-message");
      box.textContent = "The 3D view cannot be shown here (" + e.message + "). " + (renders ?
        "The static renders, opened below, show some of the same samples; the VTU files open in ParaView or 3D Slicer." :
        "Write static renders with `tissuecast evaluate MODEL --renders 3`, or open the VTU files in ParaView.");
      box.hidden = false;
      throw e;
    }
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();

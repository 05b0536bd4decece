// dla view: a self-contained WebGL2 Gaussian-splat player for one rigged dla avatar.
//
// Data (embedded by dlacli.stages.view, format "dla.view/1"): rest-pose Gaussians (means,
// quaternions w-first, sigmas, opacities, colours), per-Gaussian joint indices and weights, and
// the joint matrices M[t, j] (3x4, world from rest) of every frame. Each frame the page skins
// the Gaussians by linear blend skinning: x = (sum_j w_j M_j) x_rest on the GPU (vertex shader)
// and the orientation turned by the polar (nearest rotation) factor of the blended 3x3, as
// dlacli.stages.rig.skin does; the centres are also skinned here in JS, for sorting.
//
// Splatting follows docs/rendering.md (gsplat's classic rasterisation): EWA projection with the
// pinhole Jacobian (tangents clamped as gsplat does), cov2d + 0.3 px^2, alpha = min(0.999,
// o exp(-sigma)), fragments with alpha < 1/255 dropped. Gaussians are sorted back to front by
// camera depth (one global counting sort on 16-bit depth keys per view or frame, not per pixel)
// and blended with premultiplied alpha over the background. Cameras are dla's: world-to-camera
// 4x4 in OpenCV axes (+X right, +Y down, +Z forward), pixels fx, fy, cx, cy (docs/conventions.md).
"use strict";
(function () {
  const meta = JSON.parse(document.getElementById("dla-meta").textContent);
  const html = document.documentElement;
  const canvas = document.getElementById("dla-canvas");
  const hud = document.getElementById("dla-hud");
  const info = document.getElementById("dla-info");
  const playButton = document.getElementById("dla-play");
  const slider = document.getElementById("dla-frame");
  const label = document.getElementById("dla-label");
  const followBox = document.getElementById("dla-follow");
  const NEAR = 0.01; // docs/rendering.md: culled at camera depth < 0.01 m

  let resolveReady;
  const api = {
    meta,
    ready: new Promise((r) => (resolveReady = r)),
    setView,
    setFrame: (k) => setView({ frame: k }),
    play: () => setPlaying(true),
    pause: () => setPlaying(false),
    state: () => ({ frame: S.frame, playing: S.playing, camera: currentCamera(), orbit: { ...S.orbit } }),
    timeFrames,
  };
  window.dlaView = api;
  window.dlaReady = false;

  function fail(message) {
    html.dataset.dlaError = message;
    const box = document.getElementById("dla-error");
    box.textContent = message;
    box.style.display = "block";
    throw new Error(message);
  }

  // ------------------------------------------------------------------ data
  function base64ToBytes(text) {
    const bin = atob(text);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  async function inflate(bytes) {
    if (meta.compression === "none") return bytes;
    if (typeof DecompressionStream === "undefined") fail("This browser cannot decompress the embedded data (no DecompressionStream).");
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function halfToFloat(h) {
    const out = new Float32Array(h.length);
    for (let i = 0; i < h.length; i++) {
      const x = h[i], s = x & 0x8000 ? -1 : 1, e = (x >> 10) & 0x1f, m = x & 0x3ff;
      out[i] = e === 0 ? s * m * 5.960464477539063e-8 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * Math.pow(2, e - 15);
    }
    return out;
  }

  function arrayView(buf, spec) {
    const n = spec.shape.reduce((a, b) => a * b, 1);
    const types = { u8: Uint8Array, u16: Uint16Array, i16: Int16Array, f16: Uint16Array, f32: Float32Array };
    const view = new types[spec.dtype](buf.buffer, buf.byteOffset + spec.offset, n);
    return spec.dtype === "f16" ? halfToFloat(view) : view;
  }

  function decode(buf) {
    const a = {};
    for (const [name, spec] of Object.entries(meta.arrays)) a[name] = arrayView(buf, spec);
    const n = meta.gaussians, k = meta.k, lo = meta.position_min, step = meta.position_step;
    const pos = new Float32Array(n * 3);
    for (let i = 0; i < n * 3; i++) pos[i] = lo[i % 3] + a.positions[i] * step[i % 3];
    const quat = new Float32Array(n * 4);
    for (let i = 0; i < n; i++) {
      let q = [0, 1, 2, 3].map((c) => a.quats[4 * i + c] / 32767);
      const len = Math.hypot(...q) || 1;
      for (let c = 0; c < 4; c++) quat[4 * i + c] = q[c] / len;
    }
    const weights = new Float32Array(n * k);
    for (let i = 0; i < n * k; i++) weights[i] = a.joint_weights[i] / meta.weight_scale;
    return {
      n, k, joints: meta.joints, frames: meta.frames,
      pos, quat, scale: a.scales, opacity: a.opacities, rgb: a.rgb,
      jidx: a.joint_indices, weights, mats: a.matrices,
    };
  }

  // ------------------------------------------------------------------ GL
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true, premultipliedAlpha: true });
  if (!gl) fail("This page needs WebGL2, which this browser does not offer.");
  const floatTarget = !!gl.getExtension("EXT_color_buffer_float");
  html.dataset.dlaTarget = floatTarget ? "rgba16f" : "rgba8";
  const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
  const TEXW = Math.min(4096, maxTex);

  function dataTexture(unit, internal, format, type, values, texels, comps) {
    const rows = Math.max(1, Math.ceil(texels / TEXW));
    if (rows > maxTex) fail(`Too much data for this GPU's textures (${texels} texels, at most ${TEXW * maxTex}).`);
    const Ctor = values.constructor;
    const padded = new Ctor(TEXW * rows * comps);
    padded.set(values.subarray(0, Math.min(values.length, padded.length)));
    const tex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, TEXW, rows, 0, format, type, padded);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    for (const p of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T]) gl.texParameteri(gl.TEXTURE_2D, p, gl.CLAMP_TO_EDGE);
    return tex;
  }

  function compile(type, source) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, source);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) fail("Shader error: " + gl.getShaderInfoLog(sh));
    return sh;
  }

  function program(vs, fs) {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, vs));
    gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fs));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) fail("Shader link error: " + gl.getProgramInfoLog(p));
    return p;
  }

  function splatShaders(k4) {
    const vs = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
#define K4 ${k4}
uniform sampler2D u_pos, u_rot, u_scale, u_skin, u_mats, u_col;
uniform int u_texw, u_frame, u_joints;
uniform mat4 u_view;   // world -> camera, OpenCV axes
uniform vec4 u_intr;   // fx, fy, cx, cy (pixels)
uniform vec2 u_size;   // width, height (pixels)
in vec2 a_corner;
in uint a_index;
flat out vec4 v_color; // rgb, opacity
flat out vec3 v_conic; // a, b, c of the inverse 2D covariance
flat out vec2 v_mean;  // 2D mean, pixels (x right, y down)
ivec2 at(int i) { return ivec2(i % u_texw, i / u_texw); }
float frob(mat3 m) { return sqrt(dot(m[0], m[0]) + dot(m[1], m[1]) + dot(m[2], m[2])); }
mat3 polar(mat3 a) {   // rotation factor of a = U P: scaled Newton, X <- (g X + X^-T / g) / 2
  mat3 x = a;
  for (int it = 0; it < 6; it++) {
    mat3 xi = inverse(x);
    float g = sqrt(frob(xi) / frob(x));
    x = 0.5 * (g * x + transpose(xi) / g);
  }
  return x;
}
mat3 quatMat(vec4 q) { // (w, x, y, z) -> rotation (GLSL matrices are column-major)
  float w = q.x, x = q.y, y = q.z, z = q.w;
  return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),
              2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),
              2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));
}
void cull() { gl_Position = vec4(0.0, 0.0, 2.0, 1.0); }
void main() {
  int i = int(a_index);
  vec4 p = texelFetch(u_pos, at(i), 0);
  vec4 r0 = vec4(0.0), r1 = vec4(0.0), r2 = vec4(0.0);
  for (int g = 0; g < K4; g++) {
    vec4 idx = texelFetch(u_skin, at(i * 2 * K4 + g), 0);
    vec4 w = texelFetch(u_skin, at(i * 2 * K4 + K4 + g), 0);
    for (int c = 0; c < 4; c++) {
      if (w[c] == 0.0) continue;
      int m = (u_frame * u_joints + int(idx[c])) * 3;
      r0 += w[c] * texelFetch(u_mats, at(m), 0);
      r1 += w[c] * texelFetch(u_mats, at(m + 1), 0);
      r2 += w[c] * texelFetch(u_mats, at(m + 2), 0);
    }
  }
  vec4 rest = vec4(p.xyz, 1.0);
  vec3 mean = vec3(dot(r0, rest), dot(r1, rest), dot(r2, rest));
  mat3 blend = transpose(mat3(r0.xyz, r1.xyz, r2.xyz));
  mat3 rot = polar(blend) * quatMat(texelFetch(u_rot, at(i), 0));
  vec3 s = texelFetch(u_scale, at(i), 0).xyz;
  mat3 m = rot * mat3(s.x, 0.0, 0.0, 0.0, s.y, 0.0, 0.0, 0.0, s.z);
  mat3 wv = mat3(u_view);
  vec3 t = (u_view * vec4(mean, 1.0)).xyz;
  if (t.z < 0.01 || t.z > 1e10) { cull(); return; }
  mat3 sc = wv * m;
  mat3 cov = sc * transpose(sc);           // camera-frame 3D covariance
  float fx = u_intr.x, fy = u_intr.y, cx = u_intr.z, cy = u_intr.w;
  float tanx = 0.5 * u_size.x / fx, tany = 0.5 * u_size.y / fy;
  float u = clamp(t.x / t.z, -(cx / fx + 0.3 * tanx), (u_size.x - cx) / fx + 0.3 * tanx);
  float v = clamp(t.y / t.z, -(cy / fy + 0.3 * tany), (u_size.y - cy) / fy + 0.3 * tany);
  // pinhole Jacobian J (2x3) as the columns of a mat3x2... written out: rows j0, j1
  vec3 j0 = vec3(fx / t.z, 0.0, -fx * u / t.z);
  vec3 j1 = vec3(0.0, fy / t.z, -fy * v / t.z);
  vec3 cj0 = cov * j0, cj1 = cov * j1;
  float a = dot(j0, cj0) + 0.3, b = dot(j0, cj1), c = dot(j1, cj1) + 0.3;
  float det = a * c - b * b;
  float opacity = p.w;
  if (det <= 0.0 || opacity * 255.0 < 1.0) { cull(); return; }
  v_conic = vec3(c, -b, a) / det;
  v_mean = vec2(fx * t.x / t.z + cx, fy * t.y / t.z + cy);
  v_color = vec4(texelFetch(u_col, at(i), 0).rgb, opacity);
  // quad along the ellipse axes, out to where alpha falls below 1/255
  float mid = 0.5 * (a + c), rad = sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
  float l1 = mid + rad, l2 = max(mid - rad, 1e-6);
  vec2 e1 = abs(b) > 1e-9 ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 e2 = vec2(-e1.y, e1.x);
  float k = sqrt(2.0 * log(255.0 * opacity)) + 0.05;
  vec2 px = v_mean + a_corner.x * k * sqrt(l1) * e1 + a_corner.y * k * sqrt(l2) * e2;
  gl_Position = vec4(2.0 * px.x / u_size.x - 1.0, 1.0 - 2.0 * px.y / u_size.y, 0.0, 1.0);
}`;
    const fs = `#version 300 es
precision highp float;
uniform vec2 u_size;
flat in vec4 v_color;
flat in vec3 v_conic;
flat in vec2 v_mean;
out vec4 frag;
void main() {
  vec2 d = v_mean - vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y); // pixel centres (j + 0.5, i + 0.5)
  float sigma = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
  float alpha = min(0.999, v_color.a * exp(-sigma));
  if (sigma < 0.0 || alpha < 1.0 / 255.0) discard;
  frag = vec4(v_color.rgb * alpha, alpha);  // premultiplied
}`;
    return program(vs, fs);
  }

  const copyProgram = () => program(`#version 300 es
in vec2 a_corner; void main() { gl_Position = vec4(a_corner, 0.0, 1.0); }`, `#version 300 es
precision highp float; uniform sampler2D u_src; out vec4 frag;
void main() { frag = vec4(texelFetch(u_src, ivec2(gl_FragCoord.xy), 0).rgb, 1.0); }`);

  // ------------------------------------------------------------------ state
  const S = {
    data: null, frame: 0, playing: false, loop: true, playStart: 0, playFrom: 0, dirty: true,
    orbit: { target: meta.camera.target.slice(), distance: meta.camera.distance, azimuth: meta.camera.azimuth, elevation: meta.camera.elevation },
    fovy: meta.camera.fov, explicit: null, background: meta.background.slice(),
    skinnedFrame: -1, skinned: null, order: null, depthKeys: null, counts: new Uint32Array(65536 + 1),
  };

  // The orbit target, moved along the smoothed pelvis path while "follow" is on.
  function followOffset() {
    const path = meta.camera.follow;
    return followBox.checked && path && path[S.frame] ? path[S.frame] : [0, 0, 0];
  }

  function orbitCamera(width, height) {
    const o = S.orbit, az = (o.azimuth * Math.PI) / 180, el = (o.elevation * Math.PI) / 180;
    const back = [Math.cos(el) * Math.sin(az), -Math.cos(el) * Math.cos(az), Math.sin(el)];
    const shift = followOffset();
    const eye = o.target.map((t, c) => t + shift[c] + o.distance * back[c]);
    let right = cross([0, 0, 1], back);
    right = scaleVec(right, 1 / (Math.hypot(...right) || 1));
    const up = cross(back, right);
    const rows = [right, up.map((x) => -x), back.map((x) => -x)]; // OpenCV: x right, y down, z forward
    const viewmat = [];
    for (const r of rows) viewmat.push(r[0], r[1], r[2], -(r[0] * eye[0] + r[1] * eye[1] + r[2] * eye[2]));
    viewmat.push(0, 0, 0, 1);
    const f = (0.5 * height) / Math.tan((S.fovy * Math.PI) / 360);
    return { viewmat, fx: f, fy: f, cx: width / 2, cy: height / 2, width, height };
  }

  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function scaleVec(a, s) { return a.map((x) => x * s); }

  function currentCamera() {
    if (S.explicit) return S.explicit;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    return orbitCamera(w, h);
  }

  // An explicit camera stays until the user drags: then the orbit takes over from where it is.
  function explicitToOrbit() {
    if (!S.explicit) return;
    const m = S.explicit.viewmat, R = [m.slice(0, 3), m.slice(4, 7), m.slice(8, 11)], t = [m[3], m[7], m[11]];
    const eye = [0, 1, 2].map((c) => -(R[0][c] * t[0] + R[1][c] * t[1] + R[2][c] * t[2]));
    const fwd = R[2];
    const shift = followOffset();
    const toTarget = S.orbit.target.map((x, c) => x + shift[c] - eye[c]);
    let d = toTarget[0] * fwd[0] + toTarget[1] * fwd[1] + toTarget[2] * fwd[2];
    if (!(d > 0.1)) d = meta.camera.distance;
    S.orbit.target = eye.map((e, c) => e + d * fwd[c] - shift[c]);
    S.orbit.distance = d;
    S.orbit.elevation = (Math.asin(Math.max(-1, Math.min(1, -fwd[2]))) * 180) / Math.PI;
    S.orbit.azimuth = (Math.atan2(-fwd[0], fwd[1]) * 180) / Math.PI;
    S.explicit = null;
    canvas.style.width = canvas.style.height = "";
  }

  // ------------------------------------------------------------------ skinning + sorting (JS)
  function skinCentres(frame) {
    if (S.skinnedFrame === frame) return S.skinned;
    const D = S.data, n = D.n, k = D.k, J = D.joints, mats = D.mats, base = frame * J * 12;
    const out = S.skinned || new Float32Array(n * 3);
    for (let i = 0; i < n; i++) {
      const x = D.pos[3 * i], y = D.pos[3 * i + 1], z = D.pos[3 * i + 2];
      let px = 0, py = 0, pz = 0;
      for (let s = 0; s < k; s++) {
        const w = D.weights[i * k + s];
        if (w === 0) continue;
        const o = base + D.jidx[i * k + s] * 12;
        px += w * (mats[o] * x + mats[o + 1] * y + mats[o + 2] * z + mats[o + 3]);
        py += w * (mats[o + 4] * x + mats[o + 5] * y + mats[o + 6] * z + mats[o + 7]);
        pz += w * (mats[o + 8] * x + mats[o + 9] * y + mats[o + 10] * z + mats[o + 11]);
      }
      out[3 * i] = px; out[3 * i + 1] = py; out[3 * i + 2] = pz;
    }
    S.skinned = out;
    S.skinnedFrame = frame;
    return out;
  }

  // Back to front by camera depth: one counting sort on 16-bit keys (far = 0).
  function sortGaussians(cam) {
    const n = S.data.n, p = skinCentres(S.frame), v = cam.viewmat;
    const keys = S.depthKeys || (S.depthKeys = new Uint16Array(n));
    const depth = S.depth || (S.depth = new Float32Array(n));
    let lo = Infinity, hi = -Infinity;
    for (let i = 0; i < n; i++) {
      const z = v[8] * p[3 * i] + v[9] * p[3 * i + 1] + v[10] * p[3 * i + 2] + v[11];
      depth[i] = z;
      if (z >= NEAR) { if (z < lo) lo = z; if (z > hi) hi = z; }
    }
    const order = S.order || (S.order = new Uint32Array(n));
    const counts = S.counts;
    counts.fill(0);
    const scale = hi > lo ? 65535 / (hi - lo) : 0;
    let visible = 0;
    for (let i = 0; i < n; i++) {
      const z = depth[i];
      if (!(z >= NEAR)) { keys[i] = 0; continue; }
      const key = Math.min(65535, Math.max(0, Math.floor((hi - z) * scale)));
      keys[i] = key;
      counts[key + 1]++;
      visible++;
    }
    for (let b = 1; b <= 65536; b++) counts[b] += counts[b - 1];
    for (let i = 0; i < n; i++) if (depth[i] >= NEAR) order[counts[keys[i]]++] = i;
    return visible;
  }

  // ------------------------------------------------------------------ draw
  let G = null;

  function setupGL(D) {
    const prog = splatShaders(Math.ceil(D.k / 4));
    const k4 = Math.ceil(D.k / 4);
    const posOp = new Float32Array(D.n * 4), scale4 = new Float32Array(D.n * 4), col4 = new Uint8Array(D.n * 4);
    for (let i = 0; i < D.n; i++) {
      posOp.set([D.pos[3 * i], D.pos[3 * i + 1], D.pos[3 * i + 2], D.opacity[i] / 255], 4 * i);
      scale4.set([D.scale[3 * i], D.scale[3 * i + 1], D.scale[3 * i + 2], 0], 4 * i);
      col4.set([D.rgb[3 * i], D.rgb[3 * i + 1], D.rgb[3 * i + 2], 255], 4 * i);
    }
    const skin = new Float32Array(D.n * 8 * k4);
    for (let i = 0; i < D.n; i++) for (let s = 0; s < D.k; s++) {
      skin[i * 8 * k4 + s] = D.jidx[i * D.k + s];
      skin[i * 8 * k4 + 4 * k4 + s] = D.weights[i * D.k + s];
    }
    const mats4 = D.mats; // [T, J, 3, 4] rows: already 4 floats a texel
    const F = gl.FLOAT, RGBA = gl.RGBA;
    const tex = {
      u_pos: dataTexture(0, gl.RGBA32F, RGBA, F, posOp, D.n, 4),
      u_rot: dataTexture(1, gl.RGBA32F, RGBA, F, D.quat, D.n, 4),
      u_scale: dataTexture(2, gl.RGBA32F, RGBA, F, scale4, D.n, 4),
      u_col: dataTexture(3, gl.RGBA8, RGBA, gl.UNSIGNED_BYTE, col4, D.n, 4),
      u_skin: dataTexture(4, gl.RGBA32F, RGBA, F, skin, D.n * 2 * k4, 4),
      u_mats: dataTexture(5, gl.RGBA32F, RGBA, F, mats4, D.frames * D.joints * 3, 4),
    };
    gl.useProgram(prog);
    Object.keys(tex).forEach((name, unit) => gl.uniform1i(gl.getUniformLocation(prog, name), unit));
    gl.uniform1i(gl.getUniformLocation(prog, "u_texw"), TEXW);
    gl.uniform1i(gl.getUniformLocation(prog, "u_joints"), D.joints);
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const corners = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    const aCorner = gl.getAttribLocation(prog, "a_corner");
    gl.enableVertexAttribArray(aCorner);
    gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
    const indices = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, indices);
    gl.bufferData(gl.ARRAY_BUFFER, D.n * 4, gl.DYNAMIC_DRAW);
    const aIndex = gl.getAttribLocation(prog, "a_index");
    gl.enableVertexAttribArray(aIndex);
    gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(aIndex, 1);
    gl.bindVertexArray(null);
    const copy = copyProgram();
    const copyVao = gl.createVertexArray();
    gl.bindVertexArray(copyVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    const cCorner = gl.getAttribLocation(copy, "a_corner");
    gl.enableVertexAttribArray(cCorner);
    gl.vertexAttribPointer(cCorner, 2, gl.FLOAT, false, 0, 0);
    gl.bindVertexArray(null);
    const uni = (name) => gl.getUniformLocation(prog, name);
    G = { prog, vao, indices, copy, copyVao, tex, fbo: null, fboTex: null, fboSize: [0, 0],
          u: { view: uni("u_view"), intr: uni("u_intr"), size: uni("u_size"), frame: uni("u_frame") } };
  }

  // Blending in an RGBA16F target (when the GPU can render to float) keeps the many
  // semi-transparent layers from being rounded to 8 bits at every step; one copy to the canvas.
  function target(w, h) {
    if (!floatTarget || G.noFloat) return null;
    if (G.fboSize[0] !== w || G.fboSize[1] !== h) {
      if (G.fbo) { gl.deleteFramebuffer(G.fbo); gl.deleteTexture(G.fboTex); }
      G.fboTex = gl.createTexture();
      gl.activeTexture(gl.TEXTURE6);
      gl.bindTexture(gl.TEXTURE_2D, G.fboTex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, w, h, 0, gl.RGBA, gl.HALF_FLOAT, null);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      G.fbo = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, G.fbo);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, G.fboTex, 0);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
        gl.bindFramebuffer(gl.FRAMEBUFFER, null);
        G.fbo = null;
        G.noFloat = true;
        html.dataset.dlaTarget = "rgba8";
        return null;
      }
      G.fboSize = [w, h];
    }
    return G.fbo;
  }

  function draw() {
    const cam = currentCamera();
    if (canvas.width !== cam.width || canvas.height !== cam.height) {
      canvas.width = cam.width;
      canvas.height = cam.height;
    }
    const visible = sortGaussians(cam);
    gl.bindBuffer(gl.ARRAY_BUFFER, G.indices);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, S.order, 0, visible);
    const fbo = target(cam.width, cam.height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.viewport(0, 0, cam.width, cam.height);
    const bg = S.background;
    gl.clearColor(bg[0], bg[1], bg[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(G.prog);
    const v = cam.viewmat; // row-major -> column-major for GL
    gl.uniformMatrix4fv(G.u.view, false, new Float32Array([v[0], v[4], v[8], v[12], v[1], v[5], v[9], v[13], v[2], v[6], v[10], v[14], v[3], v[7], v[11], v[15]]));
    gl.uniform4f(G.u.intr, cam.fx, cam.fy, cam.cx, cam.cy);
    gl.uniform2f(G.u.size, cam.width, cam.height);
    gl.uniform1i(G.u.frame, S.frame);
    gl.bindVertexArray(G.vao);
    if (visible > 0) gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, visible);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
    if (fbo) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, cam.width, cam.height);
      gl.useProgram(G.copy);
      gl.activeTexture(gl.TEXTURE6);
      gl.bindTexture(gl.TEXTURE_2D, G.fboTex);
      gl.uniform1i(gl.getUniformLocation(G.copy, "u_src"), 6);
      gl.bindVertexArray(G.copyVao);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      gl.bindVertexArray(null);
    }
    S.dirty = false;
  }

  // ------------------------------------------------------------------ view API, URL hash
  function rowMajor16(m) {
    const flat = Array.isArray(m[0]) ? m.flat() : Array.from(m);
    if (flat.length !== 16 || !flat.every(Number.isFinite)) throw new Error("viewmat must be 16 finite numbers (4x4, row-major)");
    return flat.map(Number);
  }

  // setView({viewmat (4x4 world-to-camera, OpenCV, row-major), fx, fy, cx, cy, width, height,
  // frame, background: [r, g, b]}): any subset; resolves once that view is drawn.
  function setView(opts) {
    return api.ready.then(() => {
      window.dlaReady = false;
      delete html.dataset.dlaReady;
      if (opts.viewmat !== undefined) {
        const cam = { viewmat: rowMajor16(opts.viewmat) };
        const base = S.explicit || currentCamera();
        for (const key of ["fx", "fy", "cx", "cy", "width", "height"]) cam[key] = opts[key] !== undefined ? Number(opts[key]) : base[key];
        cam.width = Math.round(cam.width);
        cam.height = Math.round(cam.height);
        S.explicit = cam;
        const dpr = window.devicePixelRatio || 1;
        canvas.style.width = `${cam.width / dpr}px`;
        canvas.style.height = `${cam.height / dpr}px`;
      }
      if (opts.background !== undefined) S.background = Array.from(opts.background, Number);
      if (opts.frame !== undefined) showFrame(Number(opts.frame));
      if (opts.ui !== undefined) hud.style.display = info.style.display = opts.ui ? "" : "none";
      draw();
      gl.finish();
      window.dlaReady = true;
      html.dataset.dlaReady = String(S.frame);
      return api.state();
    });
  }

  // timeFrames(count): draw `count` successive motion frames as fast as the browser can (each one
  // skinned + sorted in JS, drawn, and read back: a one-pixel readPixels waits until the frame is
  // drawn, where Chromium's gl.finish() returns before its GPU process has drawn it) and return
  // {fps, js_ms, gl_ms}: the frames per second of playback when nothing waits for the display, and
  // the median milliseconds per frame of the JS part (skinning the centres + the depth sort) and of
  // the rest (draw + read-back); the page then shows the frame it showed before (`dla bench speed
  // --suite view`).
  function timeFrames(count) {
    return api.ready.then(() => {
      const was = S.playing, from = S.frame, frames = S.data.frames;
      const median = (x) => x.slice().sort((p, q) => p - q)[x.length >> 1];
      setPlaying(false);
      const whole = [], js = [];
      const probe = new Uint8Array(4);
      const t0 = performance.now();
      for (let i = 1; i <= count; i++) {
        showFrame((from + i) % frames);
        const a = performance.now();
        draw();
        gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, probe);
        whole.push(performance.now() - a);
      }
      const fps = (count * 1000) / (performance.now() - t0);
      for (let i = 1; i <= count; i++) {
        S.skinnedFrame = -1;
        S.frame = (from + i) % frames;
        const a = performance.now();
        sortGaussians(currentCamera());
        js.push(performance.now() - a);
      }
      showFrame(from);
      setPlaying(was);
      return { fps, js_ms: median(js), gl_ms: Math.max(0, median(whole) - median(js)) };
    });
  }

  function viewFromHash() {
    const params = new URLSearchParams(location.hash.slice(1) || location.search.slice(1));
    const opts = {};
    const nums = (key) => params.get(key).split(",").map(Number);
    if (params.has("viewmat")) opts.viewmat = nums("viewmat");
    if (params.has("intrinsics")) [opts.fx, opts.fy, opts.cx, opts.cy] = nums("intrinsics");
    if (params.has("size")) [opts.width, opts.height] = nums("size");
    if (params.has("frame")) opts.frame = Number(params.get("frame"));
    if (params.has("background")) opts.background = nums("background");
    if (params.has("ui")) opts.ui = params.get("ui") !== "0";
    if (params.has("follow")) followBox.checked = params.get("follow") !== "0";
    if (params.has("play")) opts.play = params.get("play") !== "0";
    if (params.has("loop")) S.loop = params.get("loop") !== "0";
    return opts;
  }

  // ------------------------------------------------------------------ playback + controls
  function showFrame(k) {
    const last = S.data.frames - 1;
    S.frame = Math.max(0, Math.min(last, Math.round(k) || 0));
    slider.value = String(S.frame);
    label.textContent = `${S.frame + 1} / ${S.data.frames}`;
    html.dataset.dlaFrame = String(S.frame);
    S.dirty = true;
  }

  function setPlaying(on) {
    if (on && !S.loop && S.frame === S.data.frames - 1) showFrame(0);
    S.playing = on && S.data.frames > 1;
    S.playStart = performance.now();
    S.playFrom = S.frame;
    playButton.textContent = S.playing ? "pause" : "play";
  }

  function tick(now) {
    if (S.playing) {
      let k = S.playFrom + Math.floor(((now - S.playStart) / 1000) * meta.fps);
      if (!S.loop && k >= S.data.frames - 1) {
        showFrame(S.data.frames - 1);
        setPlaying(false);
      } else if (k % S.data.frames !== S.frame) showFrame(k % S.data.frames);
    }
    if (S.dirty) draw();
    requestAnimationFrame(tick);
  }

  function controls() {
    let drag = null;
    canvas.addEventListener("contextmenu", (e) => e.preventDefault());
    canvas.addEventListener("pointerdown", (e) => {
      explicitToOrbit();
      drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.button === 1 || e.shiftKey };
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y, o = S.orbit;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.pan) {
        const cam = currentCamera(), v = cam.viewmat, dpr = window.devicePixelRatio || 1;
        const perPixel = (o.distance / cam.fy) * dpr;
        for (let c = 0; c < 3; c++) o.target[c] += perPixel * (-dx * v[c] - dy * v[4 + c]);
      } else {
        o.azimuth -= dx * 0.4;
        o.elevation = Math.max(-89, Math.min(89, o.elevation + dy * 0.4));
      }
      S.dirty = true;
    });
    const end = () => (drag = null);
    canvas.addEventListener("pointerup", end);
    canvas.addEventListener("pointercancel", end);
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      explicitToOrbit();
      S.orbit.distance = Math.max(0.05, Math.min(1000, S.orbit.distance * Math.exp(e.deltaY * 0.001)));
      S.dirty = true;
    }, { passive: false });
    playButton.addEventListener("click", () => setPlaying(!S.playing));
    slider.addEventListener("input", () => { setPlaying(false); showFrame(Number(slider.value)); });
    document.getElementById("dla-reset").addEventListener("click", resetView);
    followBox.addEventListener("change", () => { explicitToOrbit(); S.dirty = true; });
    window.addEventListener("keydown", (e) => {
      if (e.target !== document.body && e.target !== canvas) return;
      if (e.key === " ") { setPlaying(!S.playing); e.preventDefault(); }
      else if (e.key === "ArrowRight") { setPlaying(false); showFrame((S.frame + 1) % S.data.frames); }
      else if (e.key === "ArrowLeft") { setPlaying(false); showFrame((S.frame - 1 + S.data.frames) % S.data.frames); }
      else if (e.key === "r" || e.key === "R") resetView();
    });
    window.addEventListener("resize", () => (S.dirty = true));
    window.addEventListener("hashchange", () => setView(viewFromHash()));
  }

  function resetView() {
    S.explicit = null;
    canvas.style.width = canvas.style.height = "";
    S.orbit = { target: meta.camera.target.slice(), distance: meta.camera.distance, azimuth: meta.camera.azimuth, elevation: meta.camera.elevation };
    S.dirty = true;
  }

  // ------------------------------------------------------------------ start
  async function start() {
    const raw = await inflate(base64ToBytes(document.getElementById("dla-data").textContent.trim()));
    S.data = decode(raw);
    setupGL(S.data);
    slider.max = String(S.data.frames - 1);
    if (S.data.frames < 2) playButton.disabled = slider.disabled = true;
    const path = meta.camera.follow || [];
    const travel = path.reduce((m, p) => Math.max(m, Math.hypot(p[0], p[1], p[2])), 0);
    followBox.checked = travel > 0.2;
    followBox.parentElement.style.display = travel > 0 ? "" : "none";
    info.textContent = `${meta.title} · ${S.data.n.toLocaleString("en")} Gaussians · ${S.data.frames} frame${S.data.frames > 1 ? "s" : ""} at ${meta.fps} fps — drag: orbit · right/shift-drag: pan · wheel: zoom · space: play · arrows: step · R: reset`;
    showFrame(0);
    controls();
    resolveReady();
    const opts = viewFromHash();
    await setView(opts);
    if (opts.play ?? (meta.autoplay && opts.viewmat === undefined && opts.frame === undefined)) setPlaying(true);
    requestAnimationFrame(tick);
  }

  start().catch((err) => { if (!html.dataset.dlaError) { html.dataset.dlaError = String(err); console.error(err); } });
})();

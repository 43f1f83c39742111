// refnpr view: ray-marches a refnpr field in WebGL2 with refnpr's own
// arithmetic (src/field/march.rs walk, src/field/host_render.rs
// render_rays): samples at t0 + (k + 0.5) step, step = `step` lattice units
// along the ray, trilinear density over the cell's 8 lattice points (empty
// points count as zero), colour from the SH coefficients interpolated over
// the active points (renormalised), alpha 1 - exp(-relu(sigma) step), the
// ray stopped below the transmittance threshold, the background behind: the
// far map (src/field/environment.rs: equirectangular, z up, bilinear between
// texel centres, wrapping in azimuth) or the constant colour as a 1x1 map.
// The field comes packed by src/view/pack.rs (read its comment for the layout).
'use strict';

const $ = id => document.getElementById(id);

const VERTEX = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}`;

// The fragment shader for one field: its SH degree and texture count are
// compiled in (sampler arrays are indexed by constants only in GLSL ES 3.0).
function fragmentSource(h) {
  const BRICK = h.brick;
  const nb = [1, 4, 9, 16][h.sh_degree];
  const textures = h.sh_textures;
  const samplers = [...Array(textures).keys()].map(i => `uniform highp sampler3D u_sh${i};`).join('\n');
  const accumulate = [...Array(textures).keys()]
    .map(i => `s[${i}] += cw[c] * texelFetch(u_sh${i}, tc[c], 0);`).join('\n        ');
  const coeff = j => `s[${j >> 2}][${j & 3}]`;
  const channel = ch => [...Array(nb).keys()].map(b => `${coeff(ch * nb + b)} * basis[${b}]`).join(' + ');
  return `#version 300 es
precision highp float;
precision highp int;
uniform highp isampler3D u_index;
uniform highp sampler3D u_density;
${samplers}
uniform mat4 u_c2w;
uniform vec4 u_k;        // fx, fy, cx, cy
uniform float u_height;  // the image's height in pixels
uniform vec3 u_bmin, u_bmax, u_voxel;
uniform ivec3 u_res;
uniform ivec3 u_atlas;   // bricks per side
uniform highp sampler2D u_far;
uniform vec4 u_ndc;      // width, height, focal, near
uniform float u_step, u_sigma_threshold, u_log_stop;
uniform int u_max_samples;
out vec4 out_colour;

const float C0 = 0.2820948;
const float C1 = 0.4886025;

void basis_of(vec3 d, out float basis[${Math.max(nb, 1)}]) {
  basis[0] = C0;
  ${nb >= 4 ? 'basis[1] = -C1 * d.y; basis[2] = C1 * d.z; basis[3] = -C1 * d.x;' : ''}
  ${nb >= 9 ? `basis[4] = 1.0925484 * d.x * d.y; basis[5] = -1.0925484 * d.y * d.z;
  basis[6] = 0.31539157 * (2.0 * d.z * d.z - d.x * d.x - d.y * d.y);
  basis[7] = -1.0925484 * d.x * d.z; basis[8] = 0.5462742 * (d.x * d.x - d.y * d.y);` : ''}
}

// Environment::colour: the far map in world direction d.
vec3 far_colour(vec3 d) {
  const float PI = 3.14159265358979;
  ivec2 size = textureSize(u_far, 0);
  d = normalize(d);
  float u = (atan(d.y, d.x) + PI) / (2.0 * PI) * float(size.x) - 0.5;
  float v = acos(clamp(d.z, -1.0, 1.0)) / PI * float(size.y) - 0.5;
  float u0 = floor(u), v0 = floor(v);
  float fu = u - u0, fv = v - v0;
  int c0 = int(mod(u0, float(size.x))), c1 = int(mod(u0 + 1.0, float(size.x)));
  int r0 = clamp(int(v0), 0, size.y - 1), r1 = clamp(int(v0) + 1, 0, size.y - 1);
  vec3 a = texelFetch(u_far, ivec2(c0, r0), 0).rgb, b = texelFetch(u_far, ivec2(c1, r0), 0).rgb;
  vec3 c = texelFetch(u_far, ivec2(c0, r1), 0).rgb, e = texelFetch(u_far, ivec2(c1, r1), 0).rgb;
  return (1.0 - fu) * (1.0 - fv) * a + fu * (1.0 - fv) * b + (1.0 - fu) * fv * c + fu * fv * e;
}

int entry_of(ivec3 q) { return texelFetch(u_index, q / ${BRICK}, 0).r; }
// An entry's atlas slot (-1: the brick has no data): >= 0 as it is, <= -3
// for a brick with data whose own cells rays skip.
int slot_of(int e) { return e >= 0 ? e : (e <= -3 ? -e - 3 : -1); }

ivec3 atlas_texel(int slot, ivec3 q) {
  ivec3 brick = ivec3(slot % u_atlas.x, (slot / u_atlas.x) % u_atlas.y, slot / (u_atlas.x * u_atlas.y));
  return brick * ${BRICK} + q % ${BRICK};
}

void main() {
  // Camera::ray: the ray through the pixel's centre, y down from the top.
  vec2 pixel = vec2(gl_FragCoord.x, u_height - gl_FragCoord.y);
  vec3 d_cam = vec3((pixel.x - u_k.z) / u_k.x, -(pixel.y - u_k.w) / u_k.y, -1.0);
  vec3 dir = normalize(mat3(u_c2w) * d_cam);
  vec3 origin = u_c2w[3].xyz;
  vec3 view_dir = dir;
  if (u_ndc.w > 0.0) { // to_ndc
    float t = -(u_ndc.w + origin.z) / dir.z;
    vec3 o = origin + t * dir;
    float ax = -2.0 * u_ndc.z / u_ndc.x, ay = -2.0 * u_ndc.z / u_ndc.y;
    origin = vec3(ax * o.x / o.z, ay * o.y / o.z, 1.0 + 2.0 * u_ndc.w / o.z);
    dir = normalize(vec3(ax * (dir.x / dir.z - o.x / o.z), ay * (dir.y / dir.z - o.y / o.z), -2.0 * u_ndc.w / o.z));
  }
  vec3 colour = vec3(0.0);
  float optical = 0.0;
  // GridGeometry::intersect.
  vec3 inv = 1.0 / dir;
  vec3 ta = (u_bmin - origin) * inv, tb = (u_bmax - origin) * inv;
  float t0 = max(max(max(min(ta.x, tb.x), min(ta.y, tb.y)), min(ta.z, tb.z)), 0.0);
  float t1 = min(min(max(ta.x, tb.x), max(ta.y, tb.y)), max(ta.z, tb.z));
  if (t1 > t0) {
    float basis[${Math.max(nb, 1)}];
    basis_of(view_dir, basis);
    float step = u_step / length(dir / u_voxel);
    vec3 g_origin = (origin - u_bmin) / u_voxel - 0.5;
    vec3 g_dir = dir / u_voxel;
    ivec3 top = max(u_res - 2, ivec3(0));
    int k = 0;
    for (int n = 0; n < u_max_samples; n++) {
      float t = t0 + (float(k) + 0.5) * step;
      if (t >= t1) break;
      vec3 g = (origin + t * dir - u_bmin) / u_voxel - 0.5;
      vec3 gc = clamp(g, vec3(0.0), vec3(u_res - 1));
      ivec3 base = min(ivec3(gc), top);
      int entry = entry_of(base);
      if (entry == -2 || entry <= -3) {
        // A brick whose closure has no point of positive density: jump to the first
        // sample past it (the same positions: k is counted, not summed).
        vec3 lo = vec3((base / ${BRICK}) * ${BRICK}), hi = lo + ${BRICK}.0;
        vec3 ea = (lo - g_origin) / g_dir, eb = (hi - g_origin) / g_dir;
        float exit = min(min(max(ea.x, eb.x), max(ea.y, eb.y)), max(ea.z, eb.z));
        if (!(exit > t)) exit = t; // NaN on a face: step one sample
        k = max(k + 1, int(min(ceil((exit - t0) / step - 0.5), 1.0e8)));
        continue;
      }
      k++;
      // All 8 corners in the base's brick (3 cells in 4 per axis): one index read.
      bool one_brick = all(lessThan(base % ${BRICK}, ivec3(${BRICK - 1})));
      if (entry == -1 && one_brick) continue; // no data: no active corner
      vec3 f = gc - vec3(base);
      float w[8], dens[8];
      ivec3 tc[8];
      bool any_active = false;
      float sigma = 0.0;
      for (int c = 0; c < 8; c++) {
        ivec3 o = ivec3((c >> 2) & 1, (c >> 1) & 1, c & 1);
        ivec3 q = base + o;
        float wx = o.x == 1 ? f.x : 1.0 - f.x;
        float wy = o.y == 1 ? f.y : 1.0 - f.y;
        float wz = o.z == 1 ? f.z : 1.0 - f.z;
        w[c] = wx * wy * wz;
        int e = slot_of((one_brick || c == 0) ? entry : entry_of(q));
        dens[c] = -3.0e38;
        if (e >= 0) {
          tc[c] = atlas_texel(e, q);
          dens[c] = texelFetch(u_density, tc[c], 0).r;
        }
        bool on = dens[c] > -1.0e38;
        any_active = any_active || on;
        sigma += w[c] * (on ? dens[c] : 0.0);
      }
      if (!any_active || !(sigma > u_sigma_threshold)) continue;
      float total = 0.0;
      for (int c = 0; c < 8; c++) total += dens[c] > -1.0e38 ? w[c] : 0.0;
      float cw[8];
      for (int c = 0; c < 8; c++) cw[c] = dens[c] > -1.0e38 ? ${h.renormalised_colour ? 'w[c] / total' : 'w[c]'} : 0.0;
      vec4 s[${textures}];
      for (int i = 0; i < ${textures}; i++) s[i] = vec4(0.0);
      for (int c = 0; c < 8; c++) {
        if (dens[c] <= -1.0e38) continue;
        ${accumulate}
      }
      vec3 pre = vec3(${channel(0)}, ${channel(1)}, ${channel(2)}) + 0.5;
      float tau = max(sigma, 0.0) * step;
      float weight = exp(-optical) * (1.0 - exp(-tau));
      optical += tau;
      colour += weight * max(pre, vec3(0.0));
      if (-optical < u_log_stop) break;
    }
  }
  colour += exp(-optical) * far_colour(view_dir);
  out_colour = vec4(clamp(colour, 0.0, 1.0), 1.0);
}`;
}

// ---- a run on the GPU ----------------------------------------------------

function texture3d(gl, unit, internal, format, type, size, data) {
  const t = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(gl.TEXTURE_3D, t);
  gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage3D(gl.TEXTURE_3D, 0, internal, size[0], size[1], size[2], 0, format, type, data);
  return t;
}

function compile(gl, source, kind) {
  const s = gl.createShader(kind);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error('shader: ' + gl.getShaderInfoLog(s));
  return s;
}

// Uploads a field.bin (header length, header JSON, textures) and compiles its program.
function uploadRun(gl, buffer) {
  const headerLength = new DataView(buffer).getUint32(0, true);
  const h = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headerLength)));
  let offset = Math.ceil((4 + headerLength) / 4) * 4;
  const index = new Int32Array(buffer, offset, h.index_bytes / 4); offset += h.index_bytes;
  const density = new Float32Array(buffer, offset, h.density_bytes / 4); offset += h.density_bytes;
  const sh = new Uint16Array(buffer, offset, h.sh_bytes / 2); offset += h.sh_bytes;
  // The far map, or the constant background as a map of one texel.
  const farSize = h.far || [1, 1];
  const farRgb = h.far ? new Float32Array(buffer, offset, h.far_bytes / 4) : new Float32Array(h.background);
  const atlasSize = h.atlas.map(a => a * h.brick);
  const texels = atlasSize[0] * atlasSize[1] * atlasSize[2];
  const textures = [
    texture3d(gl, 0, gl.R32I, gl.RED_INTEGER, gl.INT, h.blocks, index),
    texture3d(gl, 1, gl.R32F, gl.RED, gl.FLOAT, atlasSize, density),
  ];
  for (let i = 0; i < h.sh_textures; i++) {
    textures.push(texture3d(gl, 2 + i, gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, atlasSize,
      sh.subarray(i * texels * 4, (i + 1) * texels * 4)));
  }
  const far = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + textures.length);
  gl.bindTexture(gl.TEXTURE_2D, far);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB32F, farSize[0], farSize[1], 0, gl.RGB, gl.FLOAT, farRgb);
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl, VERTEX, gl.VERTEX_SHADER));
  gl.attachShader(program, compile(gl, fragmentSource(h), gl.FRAGMENT_SHADER));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error('link: ' + gl.getProgramInfoLog(program));
  const bytes = h.index_bytes + h.density_bytes + h.sh_bytes + (h.far_bytes || 0);
  return { header: h, textures, far, program, bytes };
}

function releaseRun(gl, run) {
  if (!run) return;
  run.textures.forEach(t => gl.deleteTexture(t));
  gl.deleteTexture(run.far);
  gl.deleteProgram(run.program);
}

// Draws `run` seen by `cam` (refnpr's camera: c2w column-major, OpenGL axes;
// intrinsics in pixels of a cam.width x cam.height image) into the canvas.
function drawRun(gl, run, cam) {
  const h = run.header;
  const p = run.program;
  gl.useProgram(p);
  const u = name => gl.getUniformLocation(p, name);
  for (let i = 0; i < run.textures.length; i++) {
    gl.activeTexture(gl.TEXTURE0 + i);
    gl.bindTexture(gl.TEXTURE_3D, run.textures[i]);
  }
  gl.activeTexture(gl.TEXTURE0 + run.textures.length);
  gl.bindTexture(gl.TEXTURE_2D, run.far);
  gl.uniform1i(u('u_far'), run.textures.length);
  gl.uniform1i(u('u_index'), 0);
  gl.uniform1i(u('u_density'), 1);
  for (let i = 0; i < h.sh_textures; i++) gl.uniform1i(u(`u_sh${i}`), 2 + i);
  gl.uniformMatrix4fv(u('u_c2w'), false, new Float32Array(cam.c2w));
  gl.uniform4f(u('u_k'), cam.fx, cam.fy, cam.cx, cam.cy);
  gl.uniform1f(u('u_height'), cam.height);
  const g = h.geometry;
  const bmin = new Float32Array(g.bbox_min), bmax = new Float32Array(g.bbox_max);
  // voxel_size in f32, as refnpr computes it.
  const voxel = [0, 1, 2].map(a => Math.fround(Math.fround(bmax[a] - bmin[a]) / g.res[a]));
  gl.uniform3fv(u('u_bmin'), bmin);
  gl.uniform3fv(u('u_bmax'), bmax);
  gl.uniform3fv(u('u_voxel'), voxel);
  gl.uniform3iv(u('u_res'), g.res);
  gl.uniform3iv(u('u_atlas'), h.atlas);
  const ndc = h.ndc;
  gl.uniform4f(u('u_ndc'), ndc ? ndc.width : 0, ndc ? ndc.height : 0, ndc ? ndc.focal : 0, ndc ? ndc.near : 0);
  gl.uniform1f(u('u_step'), h.step);
  gl.uniform1f(u('u_sigma_threshold'), h.sigma_threshold);
  gl.uniform1f(u('u_log_stop'), Math.log(h.stop_threshold));
  // Enough samples for the lattice's diagonal at the step, with room for skips.
  const diagonal = Math.hypot(g.res[0], g.res[1], g.res[2]);
  gl.uniform1i(u('u_max_samples'), Math.ceil(2 * diagonal / h.step) + 16);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
}

// ---- the camera ----------------------------------------------------------

const v3 = {
  sub: (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]],
  add: (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]],
  scale: (a, s) => [a[0] * s, a[1] * s, a[2] * s],
  dot: (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2],
  cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
  norm: a => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; },
};

// Rotates `v` about unit axis `k` by `angle` (Rodrigues).
function rotate(v, k, angle) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return v3.add(v3.add(v3.scale(v, c), v3.scale(v3.cross(k, v), s)), v3.scale(k, v3.dot(k, v) * (1 - c)));
}

// An orbiting camera: eye, target, world up, intrinsics of a width x height view.
class Orbit {
  constructor(cam, target, up, limit) {
    this.setFrom(cam, target);
    this.up = up;
    this.limit = limit; // forward-facing: how far from the start the view may turn (radians)
  }
  setFrom(cam, target) {
    const m = cam.c2w;
    this.eye = [m[12], m[13], m[14]];
    this.target = target;
    this.intrinsics = { fx: cam.fx, fy: cam.fy, cx: cam.cx, cy: cam.cy, width: cam.width, height: cam.height };
    this.start = v3.norm(v3.sub(this.eye, this.target));
    this.exact = cam.c2w.slice(); // a dataset camera is shown with its own matrix until moved
  }
  c2w() {
    if (this.exact) return this.exact;
    const back = v3.norm(v3.sub(this.eye, this.target));
    let right = v3.cross(this.up, back);
    if (Math.hypot(...right) < 1e-6) right = [1, 0, 0];
    right = v3.norm(right);
    const up = v3.cross(back, right);
    return [...right, 0, ...up, 0, ...back, 0, ...this.eye, 1];
  }
  // The camera at `scale` of its resolution.
  camera(scale) {
    const k = this.intrinsics;
    const width = Math.max(1, Math.round(k.width * scale)), height = Math.max(1, Math.round(k.height * scale));
    const sx = width / k.width, sy = height / k.height;
    return { c2w: this.c2w(), fx: k.fx * sx, fy: k.fy * sy, cx: k.cx * sx, cy: k.cy * sy, width, height };
  }
  orbit(dx, dy) {
    this.exact = null;
    const offset = v3.sub(this.eye, this.target);
    let next = rotate(offset, v3.norm(this.up), -dx);
    const right = v3.norm(v3.cross(this.up, next));
    const turned = rotate(next, right, -dy);
    // Not over the pole.
    if (Math.abs(v3.dot(v3.norm(turned), v3.norm(this.up))) < 0.995) next = turned;
    if (this.limit && Math.acos(Math.min(1, v3.dot(v3.norm(next), this.start))) > this.limit) return;
    this.eye = v3.add(this.target, next);
  }
  pan(dx, dy) {
    this.exact = null;
    const m = this.c2w();
    const dist = Math.hypot(...v3.sub(this.eye, this.target));
    const move = v3.add(v3.scale([m[0], m[1], m[2]], -dx * dist), v3.scale([m[4], m[5], m[6]], dy * dist));
    this.eye = v3.add(this.eye, move);
    this.target = v3.add(this.target, move);
  }
  zoom(factor) {
    this.exact = null;
    this.eye = v3.add(this.target, v3.scale(v3.sub(this.eye, this.target), factor));
  }
}

// ---- the page ------------------------------------------------------------

const viewer = {
  gl: null, runs: [], names: [], cameras: [], versions: [], orbit: null,
  shown: 0, other: -1, split: 0.5, scale: 1, frameMs: 0, fullMs: 0, reloads: 0,
};

function fail(e) {
  $('error').textContent = String(e && e.stack || e);
  console.error(e);
}

async function fetchOk(url, kind) {
  const r = await fetch(url, { cache: 'no-store' });
  if (!r.ok) throw new Error(`${url}: ${r.status} ${await r.text()}`);
  return kind === 'json' ? r.json() : kind === 'text' ? r.text() : r.arrayBuffer();
}

async function loadRun(i) {
  const started = performance.now();
  const [buffer, cameras] = await Promise.all([
    fetchOk(`runs/${i}/field.bin`, 'bin'), fetchOk(`runs/${i}/cameras.json`, 'json')]);
  const run = uploadRun(viewer.gl, buffer);
  releaseRun(viewer.gl, viewer.runs[i]);
  viewer.runs[i] = run;
  viewer.cameras[i] = cameras;
  run.loadMs = performance.now() - started;
  return run;
}

// A first camera: the dataset's first test (or training) view, or one
// looking at the box's centre from outside it, z up.
// The point a dataset camera orbits about: along its view, at the box
// centre's depth (forward-facing runs: one unit ahead, their scene's scale).
function orbitTarget(run, cam) {
  const g = run.header.geometry;
  const centre = v3.scale(v3.add(g.bbox_min, g.bbox_max), 0.5);
  const m = cam.c2w;
  const forward = [-m[8], -m[9], -m[10]];
  const eye = [m[12], m[13], m[14]];
  const distance = run.header.ndc ? 1 : Math.max(1e-3, v3.dot(v3.sub(centre, eye), forward));
  return v3.add(eye, v3.scale(forward, distance));
}

function firstCamera(run, cameras) {
  const views = cameras.test.length ? cameras.test : cameras.train;
  const g = run.header.geometry;
  const centre = v3.scale(v3.add(g.bbox_min, g.bbox_max), 0.5);
  if (views.length) {
    const cam = views[0];
    const m = cam.c2w;
    const ndc = !!run.header.ndc;
    const up = ndc ? [m[4], m[5], m[6]] : (Math.abs(m[6]) > Math.abs(m[5]) ? [0, 0, Math.sign(m[6]) || 1] : [0, Math.sign(m[5]) || 1, 0]);
    return new Orbit(cam, orbitTarget(run, cam), up, ndc ? 0.35 : 0);
  }
  const radius = Math.hypot(...v3.sub(g.bbox_max, g.bbox_min));
  const eye = v3.add(centre, [0, -1.2 * radius, 0.6 * radius]);
  const back = v3.norm(v3.sub(eye, centre));
  const right = v3.norm(v3.cross([0, 0, 1], back));
  const up = v3.cross(back, right);
  const cam = { c2w: [...right, 0, ...up, 0, ...back, 0, ...eye, 1], fx: 600, fy: 600, cx: 400, cy: 400, width: 800, height: 800 };
  return new Orbit(cam, centre, [0, 0, 1], 0);
}

// Renders the shown run (and the compared one right of the split) at `cam`.
function renderAt(cam) {
  const gl = viewer.gl;
  const canvas = gl.canvas;
  if (canvas.width !== cam.width || canvas.height !== cam.height) {
    canvas.width = cam.width;
    canvas.height = cam.height;
  }
  gl.viewport(0, 0, cam.width, cam.height);
  const started = performance.now();
  const other = viewer.runs[viewer.other];
  if (other && viewer.other !== viewer.shown) {
    const at = Math.round(viewer.split * cam.width);
    gl.enable(gl.SCISSOR_TEST);
    gl.scissor(0, 0, at, cam.height);
    drawRun(gl, viewer.runs[viewer.shown], cam);
    gl.scissor(at, 0, cam.width - at, cam.height);
    drawRun(gl, other, cam);
    gl.disable(gl.SCISSOR_TEST);
  } else {
    drawRun(gl, viewer.runs[viewer.shown], cam);
  }
  const pixel = new Uint8Array(4);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, pixel); // waits for the frame
  viewer.frameMs = performance.now() - started;
}

// While the camera moves, frames are drawn at a resolution the last full
// frame's time says fits in about 50 ms (at least 1/8); the full
// resolution follows once it rests (a software renderer takes seconds).
let settle = null;
function redraw(moving) {
  if (!viewer.orbit || !viewer.runs[viewer.shown]) return;
  let scale = viewer.scale;
  if (moving && viewer.fullMs > 50) {
    scale = Math.max(scale * Math.sqrt(50 / viewer.fullMs), 0.125);
    clearTimeout(settle);
    settle = setTimeout(() => schedule(false), 300);
  }
  const cam = viewer.orbit.camera(scale);
  renderAt(cam);
  if (scale === viewer.scale) viewer.fullMs = viewer.frameMs;
  // Shown at the dataset's size, or larger when rendered larger.
  const enlarge = Math.max(1, viewer.scale);
  const display = { width: viewer.orbit.intrinsics.width * enlarge, height: viewer.orbit.intrinsics.height * enlarge };
  const canvas = viewer.gl.canvas;
  canvas.style.width = `${display.width}px`;
  canvas.style.height = `${display.height}px`;
  drawCameras(viewer.orbit.camera(1), enlarge);
  const split = $('split');
  split.style.display = viewer.other >= 0 ? 'block' : 'none';
  split.style.left = `${viewer.split * display.width}px`;
  const run = viewer.runs[viewer.shown];
  const mb = run.bytes / 1e6;
  $('status').textContent = `${cam.width}x${cam.height} · ${viewer.frameMs.toFixed(0)} ms/frame · ` +
    `${run.header.slots} bricks, ${mb.toFixed(1)} MB on the GPU · loaded in ${(run.loadMs / 1000).toFixed(1)} s`;
}

let pending = false;
let pendingMoving = false;
function schedule(moving = false) {
  pendingMoving = pendingMoving || moving;
  if (pending) return;
  pending = true;
  requestAnimationFrame(() => {
    const m = pendingMoving;
    pending = false;
    pendingMoving = false;
    try { redraw(m); } catch (e) { fail(e); }
  });
}

// ---- the dataset's cameras, drawn over the view ---------------------------

// `p` (world) in pixels of `cam`'s image and its depth (Camera::project), or null behind it.
function project(cam, p) {
  const m = cam.c2w;
  const d = v3.sub(p, [m[12], m[13], m[14]]);
  const x = v3.dot(d, [m[0], m[1], m[2]]), y = v3.dot(d, [m[4], m[5], m[6]]), z = v3.dot(d, [m[8], m[9], m[10]]);
  if (z >= -1e-6) return null;
  return [cam.fx * (x / -z) + cam.cx, -cam.fy * (y / -z) + cam.cy, -z];
}

// The cameras' centres and frusta (a tenth of the view's distance deep),
// drawn on the overlay in display pixels; remembers where each centre lands
// for clicks. Forward-facing runs' cameras are in world space, as here.
function drawCameras(cam, displayScale) {
  const overlay = $('overlay');
  const w = Math.round(cam.width * displayScale), h = Math.round(cam.height * displayScale);
  if (overlay.width !== w || overlay.height !== h) { overlay.width = w; overlay.height = h; }
  const ctx = overlay.getContext('2d');
  ctx.clearRect(0, 0, w, h);
  viewer.marks = [];
  const cams = viewer.cameras[viewer.shown];
  if (!$('showCameras').checked || !cams) return;
  const depth = 0.1 * Math.hypot(...v3.sub(viewer.orbit.eye, viewer.orbit.target));
  for (const split of ['train', 'test']) {
    ctx.strokeStyle = split === 'test' ? '#ffab40' : '#4fc3f7';
    cams[split].forEach((c, i) => {
      const m = c.c2w;
      const eye = [m[12], m[13], m[14]];
      const corner = (px, py) => {
        const dir = [(px - c.cx) / c.fx, -(py - c.cy) / c.fy, -1];
        const world = v3.add(v3.add(v3.scale([m[0], m[1], m[2]], dir[0]), v3.scale([m[4], m[5], m[6]], dir[1])), v3.scale([m[8], m[9], m[10]], dir[2]));
        return v3.add(eye, v3.scale(world, depth));
      };
      const pts = [eye, corner(0, 0), corner(c.width, 0), corner(c.width, c.height), corner(0, c.height)].map(p => project(cam, p));
      // Behind the view, or so near that its frustum would sprawl over it.
      if (pts.some(p => !p) || pts[0][2] < 2 * depth) return;
      const [o, ...rim] = pts.map(p => [p[0] * displayScale, p[1] * displayScale]);
      ctx.beginPath();
      for (const r of rim) { ctx.moveTo(o[0], o[1]); ctx.lineTo(r[0], r[1]); }
      rim.forEach((r, k) => (k ? ctx.lineTo(r[0], r[1]) : ctx.moveTo(r[0], r[1])));
      ctx.closePath();
      ctx.stroke();
      viewer.marks.push({ x: o[0], y: o[1], value: `${split}:${i}` });
    });
  }
}

function fillCameras() {
  const select = $('camera');
  select.innerHTML = '';
  const cams = viewer.cameras[viewer.shown] || { train: [], test: [] };
  for (const split of ['test', 'train']) {
    cams[split].forEach((c, i) => {
      const o = document.createElement('option');
      o.value = `${split}:${i}`;
      o.textContent = `${split} ${c.name}`;
      select.appendChild(o);
    });
  }
}

function bindControls(canvas) {
  let drag = null;
  canvas.addEventListener('contextmenu', e => e.preventDefault());
  canvas.addEventListener('pointerdown', e => {
    drag = { x: e.clientX, y: e.clientY, x0: e.clientX, y0: e.clientY, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointerup', e => {
    // A click (no drag) near a drawn camera looks through it.
    const moved = drag && Math.hypot(e.clientX - drag.x0, e.clientY - drag.y0) > 3;
    drag = null;
    if (moved) return;
    const r = canvas.getBoundingClientRect();
    const hit = (viewer.marks || []).find(m => Math.hypot(m.x - (e.clientX - r.left), m.y - (e.clientY - r.top)) < 8);
    if (hit) {
      $('camera').value = hit.value;
      $('camera').dispatchEvent(new Event('change'));
    }
  });
  canvas.addEventListener('pointermove', e => {
    if (!drag) return;
    const size = Math.max(canvas.clientWidth, 1);
    const dx = (e.clientX - drag.x) / size, dy = (e.clientY - drag.y) / size;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) viewer.orbit.pan(dx, dy); else viewer.orbit.orbit(dx * Math.PI, dy * Math.PI);
    schedule(true);
  });
  canvas.addEventListener('wheel', e => { e.preventDefault(); viewer.orbit.zoom(Math.exp(e.deltaY * 0.001)); schedule(true); }, { passive: false });
  $('camera').addEventListener('change', e => {
    const [split, i] = e.target.value.split(':');
    const cam = viewer.cameras[viewer.shown][split][Number(i)];
    viewer.orbit.setFrom(cam, orbitTarget(viewer.runs[viewer.shown], cam));
    schedule();
  });
  $('scale').addEventListener('change', e => { viewer.scale = Number(e.target.value); schedule(); });
  $('showCameras').addEventListener('change', () => schedule());
  $('splitAt').addEventListener('input', e => { viewer.split = Number(e.target.value); schedule(); });
  $('run').addEventListener('change', e => { viewer.shown = Number(e.target.value); fillCameras(); schedule(); });
  $('other').addEventListener('change', async e => {
    viewer.other = e.target.value === '' ? -1 : Number(e.target.value);
    if (viewer.other >= 0 && !viewer.runs[viewer.other]) await loadRun(viewer.other).catch(fail);
    schedule();
  });
  $('shot').addEventListener('click', () => {
    redraw();
    const a = document.createElement('a');
    a.download = `${viewer.names[viewer.shown]}.png`;
    a.href = viewer.gl.canvas.toDataURL('image/png');
    a.click();
  });
}

// Live: reloads a run whose checkpoint changed, keeping the camera.
async function poll() {
  for (let i = 0; i < viewer.names.length; i++) {
    if (!viewer.runs[i]) continue;
    try {
      const version = await fetchOk(`runs/${i}/version`, 'text');
      if (viewer.versions[i] !== undefined && version !== viewer.versions[i]) {
        await loadRun(i);
        viewer.reloads += 1;
        schedule();
      }
      viewer.versions[i] = version;
    } catch (e) { /* the server went away or the file is being replaced: try again */ }
  }
  setTimeout(poll, 1000);
}

async function start() {
  const canvas = $('view');
  const gl = canvas.getContext('webgl2', { preserveDrawingBuffer: true, antialias: false });
  if (!gl) throw new Error('this browser has no WebGL2');
  viewer.gl = gl;
  const listing = await fetchOk('runs.json', 'json');
  viewer.names = listing.runs;
  listing.runs.forEach((name, i) => {
    for (const id of ['run', 'other']) {
      const o = document.createElement('option');
      o.value = String(i);
      o.textContent = name;
      $(id).appendChild(o);
    }
  });
  let run = null;
  while (!run) {
    try {
      run = await loadRun(0);
    } catch (e) {
      // A run that has not written its first checkpoint yet: wait for it.
      if (!listing.live) throw e;
      $('status').textContent = `waiting for ${listing.runs[0]}'s checkpoint…`;
      await new Promise(r => setTimeout(r, 1000));
    }
  }
  viewer.orbit = firstCamera(run, viewer.cameras[0]);
  fillCameras();
  bindControls(canvas);
  redraw();
  if (listing.live) poll();
}

// What a test drives: the page is ready when `ready` resolves; `shoot`
// renders a dataset camera exactly (its own matrix and intrinsics) and
// returns the PNG as a data URL.
window.refnpr = {
  viewer,
  ready: null,
  shoot(cam) {
    viewer.orbit.setFrom(cam, orbitTarget(viewer.runs[viewer.shown], cam));
    renderAt(viewer.orbit.camera(1));
    return viewer.gl.canvas.toDataURL('image/png');
  },
  // The canvas's pixels as drawn (RGBA, bottom row first).
  pixels() {
    const gl = viewer.gl;
    const out = new Uint8Array(gl.canvas.width * gl.canvas.height * 4);
    gl.readPixels(0, 0, gl.canvas.width, gl.canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, out);
    return out;
  },
  redraw,
  async show(i) {
    if (!viewer.runs[i]) await loadRun(i);
    viewer.shown = i;
    fillCameras();
  },
  async compare(i) { viewer.other = i; if (!viewer.runs[i]) await loadRun(i); },
};
window.refnpr.ready = start().catch(e => { fail(e); throw e; });

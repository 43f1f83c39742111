// The viewer check: opens `refnpr view`'s page (served by refnpr, or a static
// copy behind any file server) in headless Chromium, shoots it at the run's
// test cameras (`refnpr export --format cameras`) and writes one PNG per
// camera for compare.py; prints the page's load time, GPU bytes and the time
// of an 800x800 frame.
//
//   node view.mjs URL CAMERAS.json OUT_DIR [--run N] [--views N] [--frame-size 800 (0: not timed)] [--controls] [--page-shot FILE]
//                 [--live NEW_CHECKPOINT SERVED_CHECKPOINT] [--chromium PATH]
//
// --live: after the shots, NEW_CHECKPOINT replaces SERVED_CHECKPOINT (copied
// beside it, then renamed, as refnpr writes checkpoints); the page must
// notice and reload the run, and is shot again into OUT_DIR/live.
import fs from 'node:fs';
import path from 'node:path';
import puppeteer from 'puppeteer-core';

const args = process.argv.slice(2);
const take = (name, count) => {
  const i = args.indexOf(name);
  if (i < 0) return null;
  return args.splice(i, count + 1).slice(1);
};
const views = Number((take('--views', 1) || ['0'])[0]);
const run = Number((take('--run', 1) || ['0'])[0]);
const frameSize = Number((take('--frame-size', 1) || ['800'])[0]);
const live = take('--live', 2);
const interact = take('--controls', 0) !== null;
// --page-shot FILE: the whole page (controls and canvas) as PNG, comparing
// run 0 with run 1 at the split when the page serves two.
const pageShot = take('--page-shot', 1);
const chromium = (take('--chromium', 1) || [process.env.CHROMIUM || '/usr/bin/chromium'])[0];
const [url, camerasPath, outDir] = args;
if (!outDir) {
  console.error('usage: node view.mjs URL CAMERAS.json OUT_DIR [--views N] [--frame-size N] [--live NEW OLD]');
  process.exit(2);
}
const cameras = JSON.parse(fs.readFileSync(camerasPath, 'utf8'));
const chosen = cameras.test.map((c, i) => [i, c])
  .filter(([i]) => !(views > 0) || i % Math.ceil(cameras.test.length / views) === 0);

async function shootAll(page, dir) {
  fs.mkdirSync(dir, { recursive: true });
  for (const [i, cam] of chosen) {
    const data = await page.evaluate(c => window.refnpr.shoot(c), cam);
    fs.writeFileSync(path.join(dir, `${String(i).padStart(4, '0')}.png`), Buffer.from(data.split(',')[1], 'base64'));
  }
}

// --controls: the page's controls as a person uses them (the page must
// serve two runs): a drag moves the view, the camera list shows the chosen
// dataset camera exactly, so does a click on a camera drawn over the view
// (the shots are of the WebGL canvas alone, under the drawing), the
// comparison shows run 0 left of the split and
// run 1 right of it, the frame-time readout is there. Exits 1 on a failure.
async function checkControls(page) {
  const same = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);
  const pixels = () => page.evaluate(() => Array.from(window.refnpr.pixels()));
  const settle = () => page.evaluate(() => new Promise(r => requestAnimationFrame(() => setTimeout(r, 50))));
  await page.evaluate(() => { window.refnpr.viewer.other = -1; window.refnpr.viewer.shown = 0; });
  await page.select('#camera', 'test:0');
  await settle();
  const start = await pixels();
  const box = await (await page.$('#view')).boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width / 2 + 40, box.y + box.height / 2 + 10, { steps: 4 });
  await page.mouse.up();
  await page.evaluate(() => window.refnpr.redraw(false));
  const dragged = !same(start, await pixels());
  await page.select('#camera', 'test:1');
  await settle();
  const chosen = await pixels();
  const exact = await page.evaluate(i => { window.refnpr.shoot(i); return Array.from(window.refnpr.pixels()); },
    cameras.test[1]);
  const cameraList = same(chosen, exact);
  // A click on a camera drawn over the view looks through it: zoom out
  // (the wheel) until one is drawn inside the view, click it.
  let mark = null;
  for (let tries = 0; tries < 6 && !mark; tries++) {
    await page.evaluate(() => window.refnpr.redraw(false));
    mark = await page.evaluate(() => {
      const o = document.getElementById('overlay');
      const now = document.getElementById('camera').value;
      return (window.refnpr.viewer.marks || [])
        .find(m => m.value !== now && m.x > 10 && m.y > 10 && m.x < o.width - 10 && m.y < o.height - 10) || null;
    });
    if (!mark) {
      await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
      await page.mouse.wheel({ deltaY: 500 });
      await settle();
    }
  }
  let cameraClick = false;
  if (mark) {
    await page.mouse.click(box.x + mark.x, box.y + mark.y);
    await settle();
    const [split, i] = mark.value.split(':');
    const picked = await page.$eval('#camera', e => e.value);
    const clicked = await pixels();
    const target = await page.evaluate(c => { window.refnpr.shoot(c); return Array.from(window.refnpr.pixels()); },
      cameras[split][Number(i)]);
    cameraClick = picked === mark.value && same(clicked, target);
    if (!cameraClick) console.error(`camera click: ${JSON.stringify(mark)} picked ${picked}, pixels ${same(clicked, target) ? 'equal' : 'differ'}`);
  } else {
    console.error('camera click: no drawn camera inside the view');
  }
  await page.select('#other', '1');
  await page.waitForFunction('window.refnpr.viewer.runs[1] !== undefined', { timeout: 120000 });
  await page.evaluate(() => window.refnpr.redraw(false));
  const split = await pixels();
  const halves = await page.evaluate(() => {
    const v = window.refnpr.viewer;
    const w = v.gl.canvas.width, h = v.gl.canvas.height, at = Math.round(v.split * w);
    const draw = i => { v.other = -1; v.shown = i; window.refnpr.redraw(false); return window.refnpr.pixels(); };
    const [a, b] = [draw(0), draw(1)];
    v.other = 1; v.shown = 0;
    return { w, h, at, a: Array.from(a), b: Array.from(b) };
  });
  let comparison = halves.a.length === split.length;
  for (let y = 0; comparison && y < halves.h; y++) {
    for (let x = 0; x < halves.w; x++) {
      const i = (y * halves.w + x) * 4;
      const want = x < halves.at ? halves.a : halves.b;
      if (want[i] !== split[i] || want[i + 1] !== split[i + 1] || want[i + 2] !== split[i + 2]) { comparison = false; break; }
    }
  }
  const readout = await page.$eval('#status', e => e.textContent);
  const result = { dragged, cameraList, cameraClick, comparison, frameReadout: / ms\/frame/.test(readout) };
  if (!Object.values(result).every(Boolean)) {
    console.error('controls failed:', JSON.stringify(result));
    process.exitCode = 1;
  }
  return result;
}

const browser = await puppeteer.launch({
  executablePath: chromium,
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist'],
});
let failed = false;
try {
  const page = await browser.newPage();
  page.on('pageerror', e => { failed = true; console.error('page error:', e.message); });
  page.on('console', m => { if (m.type() === 'error') { failed = true; console.error('page console:', m.text()); } });
  await page.setViewport({ width: 1000, height: 1000 });
  const started = Date.now();
  await page.goto(url);
  await page.waitForFunction('window.refnpr !== undefined', { timeout: 60000 });
  await page.evaluate(() => window.refnpr.ready.then(() => true));
  await page.evaluate(i => window.refnpr.show(i), run);
  const loaded = (Date.now() - started) / 1000;
  await shootAll(page, outDir);
  // One frame at frameSize x frameSize from the first test camera (intrinsics scaled), timed.
  const frameMs = frameSize <= 0 ? null : await page.evaluate((cam, size) => {
    const s = size / cam.width;
    const big = { ...cam, width: size, height: Math.round(cam.height * s), fx: cam.fx * s, fy: cam.fy * s, cx: cam.cx * s, cy: cam.cy * s };
    window.refnpr.shoot(big); // warm
    const t = performance.now();
    window.refnpr.shoot(big);
    return performance.now() - t;
  }, chosen[0][1], frameSize);
  const gpuBytes = await page.evaluate(i => window.refnpr.viewer.runs[i].bytes, run);
  const stats = { load_seconds: loaded, gpu_bytes: gpuBytes, frame_ms: frameMs, frame_size: frameSize, views: chosen.length };
  if (interact) stats.controls = await checkControls(page);
  if (pageShot) {
    const two = await page.evaluate(() => window.refnpr.viewer.names.length > 1);
    await page.select('#camera', `test:${chosen[0][0]}`);
    if (two) {
      await page.select('#other', '1');
      await page.waitForFunction('window.refnpr.viewer.runs[1] !== undefined', { timeout: 120000 });
    }
    if (chosen[0][1].width < 400) await page.select('#scale', '2'); // small datasets shown at twice their size
    await page.evaluate(() => window.refnpr.redraw(false));
    // As wide as the view (the bar wraps to fit), at least 760 px.
    const stageBox = await (await page.$('#stage')).boundingBox();
    const width = Math.ceil(Math.max(stageBox.x + stageBox.width + 8, 760));
    await page.setViewport({ width, height: 1000 });
    const fitted = await (await page.$('#stage')).boundingBox();
    await page.screenshot({ path: pageShot[0], clip: { x: 0, y: 0, width, height: Math.ceil(fitted.y + fitted.height + 8) } });
  }
  if (live) {
    const [fresh, served] = live;
    const temporary = `${served}.viewcheck.tmp`;
    fs.copyFileSync(fresh, temporary);
    fs.renameSync(temporary, served);
    const t = Date.now();
    await page.waitForFunction('window.refnpr.viewer.reloads >= 1', { timeout: 120000, polling: 200 });
    stats.live_reload_seconds = (Date.now() - t) / 1000;
    await shootAll(page, path.join(outDir, 'live'));
  }
  console.log(JSON.stringify(stats));
} finally {
  await browser.close();
}
if (failed) process.exit(1);

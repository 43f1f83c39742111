// The splat check: opens a refnpr splat export in an independent renderer
// (@mkkellogg/gaussian-splats-3d on three.js) in headless Chromium, shoots it
// from the run's test cameras (`refnpr export --format cameras`) and writes
// the screenshots as PNGs, one per camera, for compare.py.
//
//   node check_splats.mjs SPLATS.ply CAMERAS.json OUT_DIR [--sh-degree N] [--antialiased] [--views N] [--chromium PATH]
import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath } from 'node:url';
import puppeteer from 'puppeteer-core';

const here = path.dirname(fileURLToPath(import.meta.url));
const args = process.argv.slice(2);
const flag = (name, fallback) => {
  const i = args.indexOf(name);
  if (i < 0) return fallback;
  const v = args[i + 1];
  args.splice(i, 2);
  return v;
};
const antialiased = args.includes('--antialiased');
if (antialiased) args.splice(args.indexOf('--antialiased'), 1);
const shDegree = Number(flag('--sh-degree', '0'));
const views = Number(flag('--views', '0'));
const chromium = flag('--chromium', process.env.CHROMIUM || '/usr/bin/chromium');
const [kind, filePath, camerasPath, outDir] = args;
if (!outDir || !['splat', 'mesh'].includes(kind)) {
  console.error('usage: node shoot.mjs splat|mesh FILE CAMERAS.json OUT_DIR [--sh-degree N] [--antialiased] [--views N]');
  process.exit(2);
}
const served = kind === 'splat' ? '/export.ply' : '/export.glb';
const cameras = JSON.parse(fs.readFileSync(camerasPath, 'utf8'));
// --views N: N test cameras spread evenly over the list (their index names the PNG).
const chosen = cameras.test.map((c, i) => [i, c])
  .filter(([i]) => !(views > 0) || i % Math.ceil(cameras.test.length / views) === 0);
fs.mkdirSync(outDir, { recursive: true });

// Serves this folder (the page and node_modules) and the export.
const types = { '.html': 'text/html', '.js': 'text/javascript', '.mjs': 'text/javascript' };
const server = http.createServer((req, res) => {
  const url = decodeURIComponent(new URL(req.url, 'http://x').pathname);
  if (url === '/favicon.ico') { res.writeHead(204).end(); return; }
  const file = url === served ? filePath : path.join(here, path.normalize(url));
  if (url !== served && !file.startsWith(here)) { res.writeHead(403).end(); return; }
  fs.readFile(file, (err, data) => {
    if (err) { res.writeHead(404).end(); return; }
    res.writeHead(200, { 'Content-Type': types[path.extname(file)] || 'application/octet-stream' }).end(data);
  });
});
await new Promise(r => server.listen(0, '127.0.0.1', r));
const port = server.address().port;

const browser = await puppeteer.launch({
  executablePath: chromium,
  headless: true,
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist'],
});
try {
  const page = await browser.newPage();
  page.on('pageerror', e => console.error('page error:', e.message));
  page.on('console', m => { if (m.type() === 'error') console.error('page console:', m.text()); });
  const first = cameras.test[0];
  await page.setViewport({ width: first.width, height: first.height });
  await page.goto(`http://127.0.0.1:${port}/page.html`);
  await page.waitForFunction('typeof window.load === "function"');
  const started = Date.now();
  await page.evaluate((k, u, w, h, bg, o) => window.load(k, u, w, h, bg, o),
    kind, served, first.width, first.height, cameras.background, { shDegree, antialiased });
  console.log(`loaded in ${((Date.now() - started) / 1000).toFixed(1)} s`);
  for (const [i, cam] of chosen) {
    const url = await page.evaluate(c => window.shoot(c), cam);
    fs.writeFileSync(path.join(outDir, `${String(i).padStart(4, '0')}.png`), Buffer.from(url.split(',')[1], 'base64'));
  }
  console.log(`shot ${chosen.length} views into ${outDir}`);
} finally {
  await browser.close();
  server.close();
}

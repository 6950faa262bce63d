// Frame time of the studio's view for clouds of N points, each point draw side by side (the compute
// rasteriser and the instanced quads), in headless Chromium (SwiftShader WebGPU here; a hardware GPU where
// the browser has one) or Firefox ESR (lavapipe), for BENCHMARKS.md:
//
//   PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release
//   node scripts/bench-studio.mjs [POINTS ...]   (default: 1000000 10000000; FRAMES=10,
//                                                 DRAWS=compute,quads, BROWSER=chromium|firefox)
//
// Each cloud (a 200 m street of ground, facades and noise, with RGB and log_std_combined) is generated in
// memory and served on 127.0.0.1; the studio opens it by `?url=…#draw=D`, then draws FRAMES frames back
// to back (`silvr-bench` event on #view) at 1100×900 with 2-px points, and the time per frame is printed
// as JSON with the load time (fetch + parse + upload) and the draw the worker reports it used.

import { createServer } from 'node:http';
import { createRequire } from 'node:module';
import { existsSync, readFileSync } from 'node:fs';
import { extname, join, normalize, resolve, sep } from 'node:path';
import { fileURLToPath } from 'node:url';

const ROOT = resolve(fileURLToPath(new URL('..', import.meta.url)));
const DIST = join(ROOT, 'dist');
const requireWeb = createRequire(join(ROOT, 'web', 'package.json'));
const BROWSER = process.env.BROWSER || 'chromium';
const DRAWS = (process.env.DRAWS || 'compute,quads').split(',');
const counts = process.argv.slice(2).map(Number).filter((n) => n > 0);
if (!counts.length) counts.push(1_000_000, 10_000_000);
if (!existsSync(join(DIST, 'index.html'))) throw new Error('build the studio first (trunk build --release)');

function cloud(n) {
  const header = Buffer.from(
    `ply\nformat binary_little_endian 1.0\nelement vertex ${n}\nproperty float x\nproperty float y\n` +
      'property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n' +
      'property float log_std_combined\nend_header\n',
  );
  const body = Buffer.alloc(n * 19);
  let seed = 12345;
  const rnd = () => ((seed = (seed * 1103515245 + 12345) >>> 0) / 4294967296);
  for (let i = 0; i < n; i++) {
    const o = i * 19;
    const kind = rnd();
    const x = rnd() * 200 - 100;
    let y, z;
    if (kind < 0.5) [y, z] = [rnd() * 16 - 8, 0];
    else [y, z] = [rnd() < 0.5 ? -8 : 8, rnd() * 12];
    body.writeFloatLE(x, o);
    body.writeFloatLE(y, o + 4);
    body.writeFloatLE(z, o + 8);
    body[o + 12] = 80 + 120 * rnd();
    body[o + 13] = 90 + 100 * (z / 12);
    body[o + 14] = 100;
    body.writeFloatLE(-2.5 + 0.02 * Math.abs(x) + 0.3 * rnd(), o + 15);
  }
  return Buffer.concat([header, body]);
}

const MIME = { '.html': 'text/html', '.js': 'text/javascript', '.wasm': 'application/wasm', '.css': 'text/css' };
let data = null;
const server = createServer((req, res) => {
  const raw = decodeURIComponent(new URL(req.url, 'http://x').pathname);
  const path = raw === '/' ? '/index.html' : raw;
  let body = path === '/data/cloud.ply' ? data : null;
  if (!body) {
    const file = normalize(join(DIST, path));
    if (file.startsWith(DIST + sep) && existsSync(file)) body = readFileSync(file);
  }
  if (!body) return res.writeHead(404).end();
  res.writeHead(200, { 'content-type': MIME[extname(path)] || 'application/octet-stream', 'content-length': body.length });
  res.end(body);
});
await new Promise((ok) => server.listen(0, '127.0.0.1', ok));
const base = `http://127.0.0.1:${server.address().port}`;
// One driver per browser: launch, a 1100×900 page, goto, wait for a predicate, evaluate.
async function launch() {
  if (BROWSER === 'firefox') {
    const browser = await requireWeb('puppeteer-core').launch({
      browser: 'firefox',
      executablePath: process.env.SILVR_FIREFOX || '/usr/bin/firefox-esr',
      headless: true,
      protocolTimeout: 3_600_000,
      extraPrefsFirefox: { 'dom.webgpu.enabled': true, 'gfx.webgpu.ignore-blocklist': true },
    });
    return {
      close: () => browser.close(),
      page: async () => {
        const page = await browser.newPage();
        await page.setViewport({ width: 1100, height: 900 });
        return {
          goto: (url) => page.goto(url, { waitUntil: 'load' }),
          waitFor: (fn) => page.waitForFunction(fn, { timeout: 3_600_000, polling: 200 }),
          evaluate: (fn, arg) => page.evaluate(fn, arg),
          close: () => page.close(),
        };
      },
    };
  }
  const browser = await requireWeb('playwright-core').chromium.launch({
    executablePath: process.env.SILVR_CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--enable-unsafe-webgpu', '--enable-features=Vulkan', '--use-vulkan=swiftshader', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
  return {
    close: () => browser.close(),
    page: async () => {
      const page = await browser.newPage({ viewport: { width: 1100, height: 900 } });
      return {
        goto: (url) => page.goto(url),
        waitFor: (fn) => page.waitForFunction(fn, null, { timeout: 3_600_000 }),
        evaluate: (fn, arg) => page.evaluate(fn, arg),
        close: () => page.close(),
      };
    },
  };
}

try {
  for (const n of counts) {
    data = cloud(n);
    for (const draw of DRAWS) {
      // A fresh browser per run: Firefox's GPU process did not survive a 10 M-point page after others.
      const browser = await launch();
      try {
        const page = await browser.page();
        const t0 = Date.now();
        await page.goto(`${base}/?url=${encodeURIComponent(`${base}/data/cloud.ply`)}#draw=${draw}`);
        await page.waitFor(() => document.querySelectorAll('#layers li').length > 0 || document.querySelector('#view-messages li'));
        const loadS = (Date.now() - t0) / 1000;
        const err = await page.evaluate(() => document.querySelector('#view-messages')?.textContent || '');
        if (err) throw new Error(`${n} points: ${err}`);
        await page.waitFor(() => Number(document.querySelector('#view').dataset.frames || 0) >= 1);
        const frames = Number(process.env.FRAMES || '10');
        await page.evaluate((f) => document.querySelector('#view').dispatchEvent(new CustomEvent('silvr-bench', { detail: f })), frames);
        await page.waitFor(() => document.querySelector('#view').dataset.benchMs);
        const r = await page.evaluate(() => {
          const v = document.querySelector('#view').dataset;
          const adapter = document.querySelector('#adapter')?.dataset.name;
          return { adapter, draw: v.benchDraw, ms_per_frame: Number(v.benchMs), points: Number(v.benchPoints), frames: Number(v.benchFrames) };
        });
        console.log(JSON.stringify({ browser: BROWSER, asked: draw, load_s: loadS, ...r }));
        await page.close();
      } finally {
        await browser.close();
      }
    }
  }
} finally {
  server.close();
}

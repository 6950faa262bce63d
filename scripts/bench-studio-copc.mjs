// A COPC map streamed into the studio, in headless Chromium (SwiftShader WebGPU here; a hardware GPU where
// the browser has one), for BENCHMARKS.md (issue 36):
//
//   PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release && cargo build -p silvr
//   node scripts/bench-studio-copc.mjs DIR [BUDGET ...]     (default budgets: 400000 1000000; FRAMES=5)
//
// DIR holds one .copc.laz (scripts/browser-tests.sh leaves a 20 M-point one in target/studio-scale;
// `python3 scripts/gen_cloud.py N X.ply && silvr export copc X.ply --out DIR/X.copc.laz` makes others).
// `silvr serve DIR` serves it with byte ranges on 127.0.0.1; for each budget a new page opens serve's link
// with `budget=` (and `draw=D` with DRAW=quads), and the script prints as JSON: seconds from the request to
// the first frame with points, to the view refined at rest (nothing pending), the points then loaded, ms
// per frame of FRAMES frames drawn back to back (`silvr-bench` on #view) at 1100×900 with 2-px points, the
// median and worst time from a drag to its frame over ORBIT (10) drags, and the worker's wasm heap.

import { spawn } from 'node:child_process';
import { createRequire } from 'node:module';
import { existsSync } from 'node:fs';
import { join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';

const ROOT = resolve(fileURLToPath(new URL('..', import.meta.url)));
const DIST = join(ROOT, 'dist');
const { chromium } = createRequire(join(ROOT, 'web', 'package.json'))('playwright-core');
const [dir, ...rest] = process.argv.slice(2);
if (!dir) throw new Error('usage: node scripts/bench-studio-copc.mjs DIR [BUDGET ...]');
const budgets = rest.map(Number).filter((n) => n > 0);
if (!budgets.length) budgets.push(400_000, 1_000_000);
if (!existsSync(join(DIST, 'index.html'))) throw new Error('build the studio first (trunk build --release)');
const silvr = join(process.env.CARGO_TARGET_DIR || join(ROOT, 'target'), 'debug', 'silvr');
if (!existsSync(silvr)) throw new Error(`no ${silvr}: cargo build -p silvr`);

const serve = spawn(silvr, ['serve', dir, '--port', '0', '--studio', DIST], { stdio: ['ignore', 'pipe', 'inherit'] });
const link = await new Promise((ok, fail) => {
  let out = '';
  serve.stdout.on('data', (d) => {
    out += d;
    const m = out.match(/^open: (\S+)$/m);
    if (m) ok(m[1]);
  });
  serve.on('exit', (c) => fail(new Error(`silvr serve exited (${c}): ${out}`)));
});
const browser = await chromium.launch({
  executablePath: process.env.SILVR_CHROMIUM || '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--enable-unsafe-webgpu', '--enable-features=Vulkan', '--use-vulkan=swiftshader', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
});
const wait = (page, fn, arg) => page.waitForFunction(fn, arg, { timeout: 1_800_000, polling: 50 });
try {
  for (const budget of budgets) {
    const page = await browser.newPage({ viewport: { width: 1100, height: 900 } });
    const t0 = Date.now();
    await page.goto(`${link}&budget=${budget}${process.env.DRAW ? `&draw=${process.env.DRAW}` : ''}`);
    await wait(page, () => Number(document.querySelector('#view').dataset.drawnPoints) > 0 || document.querySelector('#view-messages li'));
    const first = (Date.now() - t0) / 1000;
    const err = await page.evaluate(() => document.querySelector('#view-messages')?.textContent || '');
    if (err) throw new Error(err);
    const firstPoints = Number(await page.evaluate(() => document.querySelector('#view').dataset.drawnPoints));
    // At rest: the layer shows nothing pending, a frame has drawn what it holds, and nothing has changed for
    // 2 s (refinement starts 250 ms after the camera rests: a first frame that comes sooner is not the end).
    // `refined` is when the loaded count last changed.
    let refined = first;
    let last = '';
    for (let quiet = 0; quiet < 2000; ) {
      const now = await page.evaluate(() => {
        const l = document.querySelector('#layers li');
        const v = document.querySelector('#view').dataset;
        return l ? `${l.dataset.points}/${l.dataset.pending}/${v.drawnPoints}` : '';
      });
      const [points, pending, drawn] = now.split('/');
      if (now !== last) {
        last = now;
        quiet = 0;
        refined = (Date.now() - t0) / 1000;
      } else if (pending === '0' && points === drawn) {
        quiet += 50;
      }
      await new Promise((r) => setTimeout(r, 50));
    }
    const li = await page.evaluate(() => ({ ...document.querySelector('#layers li').dataset }));
    const frames = process.env.FRAMES || '5';
    await page.evaluate((frames) => document.querySelector('#view').dispatchEvent(new CustomEvent('silvr-bench', { detail: Number(frames) })), frames);
    await wait(page, () => document.querySelector('#view').dataset.benchMs);
    const bench = await page.evaluate(() => ({ ...document.querySelector('#view').dataset }));
    // Orbiting: ORBIT drags of 12 px, each timed from the drag to the frame of its view (the page sends a
    // view change per animation frame; the worker draws what it holds and refines only at rest).
    const box = await page.evaluate(() => {
      const r = document.querySelector('#view').getBoundingClientRect();
      return { x: r.x + r.width / 2, y: r.y + r.height / 2 };
    });
    const orbit = [];
    for (let k = 0; k < Number(process.env.ORBIT || '10'); k++) {
      const t = Date.now();
      await page.mouse.move(box.x + 12 * k, box.y);
      await page.mouse.down();
      await page.mouse.move(box.x + 12 * (k + 1), box.y, { steps: 2 });
      await page.mouse.up();
      await wait(page, () => {
        const v = document.querySelector('#view').dataset;
        return v.seq !== undefined && v.drawnSeq === v.seq;
      });
      orbit.push(Date.now() - t);
    }
    orbit.sort((a, b) => a - b);
    const adapter = await page.getAttribute('#adapter', 'data-name');
    console.log(JSON.stringify({
      map_points: Number(li.total), budget, adapter, draw: bench.benchDraw, first_frame_s: first, first_frame_points: firstPoints,
      refined_s: refined, loaded_points: Number(li.points), nodes: Number(li.nodes), ms_per_frame: Number(bench.benchMs),
      orbit_ms_median: orbit[orbit.length >> 1], orbit_ms_max: orbit[orbit.length - 1],
      worker_wasm_mb: Number(bench.benchWasmBytes) / 2 ** 20,
    }));
    await page.close();
  }
} finally {
  await browser.close();
  serve.kill();
}

// A COPC map streamed into the studio, in headless Chromium (SwiftShader WebGPU here; a hardware GPU where
// the browser has one), for BENCHMARKS.md (issue 36):
//
//   PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release && cargo build -p silvr
//   node scripts/bench-studio-copc.mjs DIR [BUDGET ...]     (default budgets: 400000 1000000; FRAMES=5)
//
// DIR holds one .copc.laz (scripts/browser-tests.sh leaves a 20 M-point one in target/studio-scale;
// `python3 scripts/gen_cloud.py N X.ply && silvr export copc X.ply --out DIR/X.copc.laz` makes others).
// `silvr serve DIR` serves it with byte ranges on 127.0.0.1; for each budget a new page opens serve's link
// with `budget=`, and the script prints as JSON: seconds from the request to the first frame with points,
// to the view refined at rest (nothing pending), the points then loaded, and ms per frame of FRAMES frames
// drawn back to back (`silvr-bench` on #view) at 1100×900 with 2-px points.

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
    await page.goto(`${link}&budget=${budget}`);
    await wait(page, () => Number(document.querySelector('#view').dataset.drawnPoints) > 0 || document.querySelector('#view-messages li'));
    const first = (Date.now() - t0) / 1000;
    const err = await page.evaluate(() => document.querySelector('#view-messages')?.textContent || '');
    if (err) throw new Error(err);
    const firstPoints = Number(await page.evaluate(() => document.querySelector('#view').dataset.drawnPoints));
    // At rest: the layer shows nothing pending and a frame has drawn what it holds.
    await wait(page, () => {
      const l = document.querySelector('#layers li');
      const v = document.querySelector('#view').dataset;
      return l && l.dataset.pending === '0' && Number(l.dataset.points) > 0 && v.drawnPoints === l.dataset.points;
    });
    const refined = (Date.now() - t0) / 1000;
    const li = await page.evaluate(() => ({ ...document.querySelector('#layers li').dataset }));
    const frames = process.env.FRAMES || '5';
    await page.evaluate((frames) => document.querySelector('#view').dispatchEvent(new CustomEvent('silvr-bench', { detail: Number(frames) })), frames);
    await wait(page, () => document.querySelector('#view').dataset.benchMs);
    const ms = Number(await page.evaluate(() => document.querySelector('#view').dataset.benchMs));
    const adapter = await page.getAttribute('#adapter', 'data-name');
    console.log(JSON.stringify({
      map_points: Number(li.total), budget, adapter, first_frame_s: first, first_frame_points: firstPoints,
      refined_s: refined, loaded_points: Number(li.points), nodes: Number(li.nodes), ms_per_frame: ms,
    }));
    await page.close();
  }
} finally {
  await browser.close();
  serve.kill();
}

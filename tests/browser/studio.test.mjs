// End-to-end test of the studio page: dist/ (from `trunk build --release`) served on 127.0.0.1 and loaded
// in headless Chromium (SwiftShader WebGPU) through playwright-core.
//
//   npm ci --prefix web && PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release
//   node --test tests/browser/
//
// Environment: SILVR_CHROMIUM (default /usr/bin/chromium); SILVR_SCREENSHOT=/tmp/studio.png saves a
// screenshot of the page after the drop.

import { after, before, describe, test } from 'node:test';
import assert from 'node:assert/strict';
import { createServer } from 'node:http';
import { createRequire } from 'node:module';
import { existsSync } from 'node:fs';
import { readFile, stat } from 'node:fs/promises';
import { extname, join, normalize, resolve, sep } from 'node:path';
import { fileURLToPath } from 'node:url';
import { randomBytes } from 'node:crypto';

const ROOT = resolve(fileURLToPath(new URL('../..', import.meta.url)));
const DIST = join(ROOT, 'dist');
const CHROMIUM = process.env.SILVR_CHROMIUM || '/usr/bin/chromium';

// Bounds: SwiftShader compiles the WGSL kernel and runs it on the CPU, 2 cores.
const STARTUP_TIMEOUT_MS = 90_000;
const STEP_TIMEOUT_MS = 30_000;

/** playwright-core lives in web/node_modules (web/package.json), not next to this file. */
function loadPlaywright() {
  const require = createRequire(join(ROOT, 'web', 'package.json'));
  try {
    return require('playwright-core');
  } catch (e) {
    throw new Error(`playwright-core is missing: run \`npm ci --prefix web\` first (${e.message})`);
  }
}

const { chromium } = loadPlaywright();

// Flags from shared/reference/toolchain.md §3: SwiftShader WebGPU in pages and workers (and canvases).
const BASE_ARGS = [
  '--no-sandbox',
  '--disable-dev-shm-usage',
  '--disable-background-networking',
  '--disable-component-update',
  '--disable-sync',
  '--no-first-run',
  '--disable-quic',
];
const WEBGPU_ARGS = [
  '--enable-unsafe-webgpu',
  '--enable-features=Vulkan',
  '--use-vulkan=swiftshader',
  '--use-angle=swiftshader',
  '--enable-unsafe-swiftshader',
];

const MIME = {
  '.html': 'text/html; charset=utf-8',
  '.js': 'text/javascript; charset=utf-8',
  '.mjs': 'text/javascript; charset=utf-8',
  '.wasm': 'application/wasm',
  '.css': 'text/css; charset=utf-8',
  '.json': 'application/json',
  '.svg': 'image/svg+xml',
  '.png': 'image/png',
  '.ico': 'image/x-icon',
};

/** Serves dist/ on 127.0.0.1 at a free port. */
async function serveDist() {
  const server = createServer(async (req, res) => {
    try {
      const url = new URL(req.url, 'http://localhost');
      let rel = decodeURIComponent(url.pathname);
      if (rel.endsWith('/')) rel += 'index.html';
      const file = normalize(join(DIST, rel));
      if (file !== DIST && !file.startsWith(DIST + sep)) {
        res.writeHead(403).end('forbidden');
        return;
      }
      const body = await readFile(file);
      res.writeHead(200, {
        'content-type': MIME[extname(file)] || 'application/octet-stream',
        'cache-control': 'no-store',
      });
      res.end(body);
    } catch {
      res.writeHead(404, { 'content-type': 'text/plain' }).end('not found');
    }
  });
  await new Promise((ok, fail) => {
    server.once('error', fail);
    server.listen(0, '127.0.0.1', ok);
  });
  return { server, url: `http://127.0.0.1:${server.address().port}/` };
}

/** Stops the server, dropping the browser's keep-alive connections so node can exit. */
function stopServer(server) {
  if (!server) return Promise.resolve();
  server.closeAllConnections();
  return new Promise((ok) => server.close(() => ok()));
}

/** Playwright gives each launch a fresh temporary profile and removes it on close. */
async function launch(args) {
  const browser = await chromium.launch({
    executablePath: CHROMIUM,
    headless: true,
    args: [...BASE_ARGS, ...args],
    timeout: STEP_TIMEOUT_MS,
  });
  return {
    browser,
    close: () => browser.close().catch(() => {}),
  };
}

/** Opens the studio and collects what the page logs, for assertion messages. */
async function openStudio(browser, url) {
  const page = await browser.newPage();
  const log = [];
  page.on('console', (m) => log.push(`[${m.type()}] ${m.text()}`));
  page.on('pageerror', (e) => log.push(`[pageerror] ${e.message}`));
  page.on('requestfailed', (r) => log.push(`[requestfailed] ${r.url()} ${r.failure()?.errorText}`));
  page.setDefaultTimeout(STEP_TIMEOUT_MS);
  await page.goto(url, { waitUntil: 'load' });
  return { page, log };
}

/** Waits until <body data-state> leaves `loading`; returns the state. */
async function settle(page, log) {
  try {
    await page.waitForFunction(() => document.body.dataset.state !== 'loading', null, {
      timeout: STARTUP_TIMEOUT_MS,
    });
  } catch (e) {
    const status = await page.textContent('#status').catch(() => '?');
    throw new Error(`the studio did not finish starting (status: ${status}); page log:\n${log.join('\n')}\n${e.message}`);
  }
  return page.evaluate(() => document.body.dataset.state);
}

before(() => {
  if (!existsSync(join(DIST, 'index.html')) || !existsSync(join(DIST, 'worker_loader.js'))) {
    throw new Error(
      `${DIST} has no studio build: run \`PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release\` ` +
        '(or scripts/browser-tests.sh) first',
    );
  }
  if (!existsSync(CHROMIUM)) {
    throw new Error(`no Chromium at ${CHROMIUM} (apt-get install chromium, or set SILVR_CHROMIUM)`);
  }
});

describe('studio with WebGPU (SwiftShader)', { timeout: 4 * STARTUP_TIMEOUT_MS }, () => {
  let server, url, chrome, page, log;

  before(async () => {
    ({ server, url } = await serveDist());
    chrome = await launch(WEBGPU_ARGS);
    ({ page, log } = await openStudio(chrome.browser, url));
  });

  after(async () => {
    await chrome?.close();
    await stopServer(server);
  });

  test('page loads and the worker reports a WebGPU adapter', async () => {
    assert.match(await page.title(), /^SiLVR Studio/);
    assert.equal(await page.textContent('h1'), 'SiLVR Studio');
    const state = await settle(page, log);
    assert.equal(state, 'ready', `state ${state}: ${await page.textContent('#error')}\n${log.join('\n')}`);
    assert.equal(await page.title(), 'SiLVR Studio — ready');
    const name = await page.getAttribute('#adapter', 'data-name');
    assert.ok(name && name.trim().length > 0, `adapter name is empty; #adapter: ${await page.textContent('#adapter')}`);
    // wgpu leaves the name empty on the web; the worker names it from GPUAdapterInfo (vendor, architecture).
    assert.notEqual(name, 'unnamed adapter');
    const text = await page.textContent('#adapter');
    assert.ok(text.includes('BrowserWebGpu'), text);
    // Headless Chromium only has SwiftShader, a CPU rasteriser.
    assert.equal(await page.getAttribute('#adapter', 'data-software'), 'true', text);
    assert.ok(text.includes('software'), text);
  });

  test('projection kernel agrees with the CPU reference', async () => {
    const get = (a) => page.getAttribute('#projection', a);
    assert.equal(await get('data-passed'), 'true', await page.textContent('#projection'));
    assert.equal(await get('data-mismatches'), '0');
    assert.ok(Number(await get('data-filled')) > 0, 'no pixel was filled');
    assert.equal(await get('data-points'), '4000');
    assert.ok((await page.textContent('#projection')).includes('agrees with the CPU reference'));
    assert.equal(await page.isHidden('#error'), true, await page.textContent('#error'));
  });

  test('the page can ask the worker for another check', async () => {
    await page.click('#rerun');
    await page.waitForFunction(() => document.querySelector('#projection').dataset.runs === '2', null, {
      timeout: STARTUP_TIMEOUT_MS,
    });
    assert.equal(await page.getAttribute('#projection', 'data-passed'), 'true');
    assert.equal(await page.getAttribute('#projection', 'data-mismatches'), '0');
    assert.equal(await page.getAttribute('#projection', 'data-points'), '20000');
    assert.equal(await page.isEnabled('#rerun'), true);
  });

  test('a dropped file shows its name and size', async () => {
    const name = 'spires front 2024-03-01.mcap';
    const bytes = randomBytes(100_000);
    const dataTransfer = await page.evaluateHandle(
      ({ b64, name }) => {
        const bin = atob(b64);
        const data = new Uint8Array(bin.length);
        for (let i = 0; i < bin.length; i++) data[i] = bin.charCodeAt(i);
        const dt = new DataTransfer();
        dt.items.add(new File([data], name, { type: 'application/octet-stream' }));
        return dt;
      },
      { b64: bytes.toString('base64'), name },
    );
    const before = page.url();
    for (const type of ['dragenter', 'dragover', 'drop']) {
      await page.dispatchEvent('#drop', type, { dataTransfer });
    }
    await page.waitForSelector('#dropped[data-name]');
    assert.equal(await page.getAttribute('#dropped', 'data-name'), name);
    assert.equal(await page.getAttribute('#dropped', 'data-bytes'), String(bytes.length));
    const text = await page.textContent('#dropped');
    assert.ok(text.includes(name), text);
    assert.ok(text.includes('100,000 bytes'), text);
    assert.equal(page.url(), before, 'the drop navigated away from the studio');
    assert.equal(await page.evaluate(() => document.body.dataset.state), 'ready');
    if (process.env.SILVR_SCREENSHOT) {
      await page.screenshot({ path: process.env.SILVR_SCREENSHOT, fullPage: true });
    }
    const errors = log.filter((l) => l.startsWith('[pageerror]') || l.startsWith('[requestfailed]'));
    assert.deepEqual(errors, [], log.join('\n'));
  });
});

describe('studio without WebGPU', { timeout: 2 * STARTUP_TIMEOUT_MS }, () => {
  test('shows a clear error and the error state', async () => {
    const { server, url } = await serveDist();
    let chrome;
    try {
      // No --enable-unsafe-webgpu (and WebGPU switched off): headless Chromium then offers no adapter.
      chrome = await launch(['--disable-features=WebGPU']);
      const { page, log } = await openStudio(chrome.browser, url);
      const state = await settle(page, log);
      assert.equal(state, 'error', log.join('\n'));
      assert.equal(await page.title(), 'SiLVR Studio — error');
      const message = await page.textContent('#error');
      assert.ok(await page.isVisible('#error'));
      assert.match(message, /needs WebGPU/, message);
      assert.equal(await page.getAttribute('#adapter', 'data-error'), 'webgpu');
      // The worker says why (navigator.gpu missing, or no adapter) and keeps wgpu's error as detail.
      const why = await page.textContent('#adapter');
      assert.match(why, /navigator\.gpu/, why);
      assert.match(why, /no GPU adapter found/, why);
      assert.equal(await page.isDisabled('#rerun'), true);
    } finally {
      await chrome?.close();
      await stopServer(server);
    }
  });
});

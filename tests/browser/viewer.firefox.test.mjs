// The studio's view in headless Firefox ESR (≥ 141; lavapipe WebGPU with two prefs) through
// puppeteer-core over WebDriver BiDi (shared/reference/browser_testing.md); the tests are in viewer.mjs.

import { createRequire } from 'node:module';
import { existsSync } from 'node:fs';
import { join } from 'node:path';
import { ROOT, collectLog, viewerSuite } from './viewer.mjs';
import { trainSuite } from './train.mjs';

const puppeteer = createRequire(join(ROOT, 'web', 'package.json'))('puppeteer-core');
const FIREFOX = process.env.SILVR_FIREFOX || '/usr/bin/firefox-esr';
if (!existsSync(FIREFOX)) {
  throw new Error(`no Firefox at ${FIREFOX} (scripts/setup.sh installs firefox-esr ≥ 141, or set SILVR_FIREFOX)`);
}

const driver = {
  name: 'Firefox',
  serve: false,
  launch: () =>
    puppeteer.launch({
      browser: 'firefox',
      executablePath: FIREFOX,
      headless: true,
      protocolTimeout: 180_000,
      extraPrefsFirefox: {
        'dom.webgpu.enabled': true,
        'gfx.webgpu.ignore-blocklist': true,
      },
    }),
  close: (b) => b?.close().catch(() => {}),
  newPage: async (browser) => {
    // A browser context per page, as Playwright gives: storage (the training card's saved runs in the
    // origin-private file system) does not leak from one test into the next.
    const context = await browser.createBrowserContext();
    const page = await context.newPage();
    page.once('close', () => context.close().catch(() => {}));
    await page.setViewport({ width: 1100, height: 900 });
    return { page, log: collectLog(page) };
  },
  goto: (page, url) => page.goto(url, { waitUntil: 'load' }),
  waitFor: (page, fn, arg, timeout) => page.waitForFunction(fn, { timeout, polling: 100 }, arg),
  evaluate: (page, fn, arg) => page.evaluate(fn, arg),
  upload: async (page, selector, path) => (await page.$(selector)).uploadFile(path),
  screenshot: async (page, selector) => Buffer.from(await (await page.$(selector)).screenshot()),
  drag: async (page, x0, y0, x1, y1) => {
    await page.mouse.move(x0, y0);
    await page.mouse.down();
    await page.mouse.move(x1, y1, { steps: 5 });
    await page.mouse.up();
  },
};

viewerSuite(driver);
trainSuite(driver);

// The studio's view in headless Chromium (SwiftShader WebGPU) through playwright-core; the tests
// themselves are in viewer.mjs and train.mjs, shared with Firefox.

import { createRequire } from 'node:module';
import { join } from 'node:path';
import { ROOT, collectLog, viewerSuite } from './viewer.mjs';
import { trainSuite } from './train.mjs';

const { chromium } = createRequire(join(ROOT, 'web', 'package.json'))('playwright-core');
const CHROMIUM = process.env.SILVR_CHROMIUM || '/usr/bin/chromium';

const driver = {
  name: 'Chromium',
  serve: true,
  launch: () =>
    chromium.launch({
      executablePath: CHROMIUM,
      headless: true,
      args: [
        '--no-sandbox',
        '--disable-dev-shm-usage',
        '--disable-background-networking',
        '--no-first-run',
        '--enable-unsafe-webgpu',
        '--enable-features=Vulkan',
        '--use-vulkan=swiftshader',
        '--use-angle=swiftshader',
        '--enable-unsafe-swiftshader',
      ],
    }),
  close: (b) => b?.close().catch(() => {}),
  newPage: async (browser) => {
    const page = await browser.newPage({ viewport: { width: 1100, height: 900 } });
    return { page, log: collectLog(page) };
  },
  goto: (page, url) => page.goto(url, { waitUntil: 'load' }),
  waitFor: (page, fn, arg, timeout) => page.waitForFunction(fn, arg, { timeout }),
  evaluate: (page, fn, arg) => page.evaluate(fn, arg),
  // A folder path fills a `webkitdirectory` input with the folder's files and their relative paths.
  upload: (page, selector, path) => page.setInputFiles(selector, path),
  folderUpload: true,
  screenshot: (page, selector) => page.locator(selector).screenshot(),
  drag: async (page, x0, y0, x1, y1) => {
    await page.mouse.move(x0, y0);
    await page.mouse.down();
    await page.mouse.move(x1, y1, { steps: 5 });
    await page.mouse.up();
  },
};

viewerSuite(driver);
trainSuite(driver);

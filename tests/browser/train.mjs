// Training a submap in the studio's worker, end to end, written once for both browsers (the drivers in
// viewer.*.test.mjs call `trainSuite` with the same driver as the view's tests).
//
// Fixtures (left in $SILVR_STUDIO_FIXTURES by the native test tests/tests/submap.rs): micro.tar (the micro
// world packed by `silvr pack`), micro-native.json (the native WGSL run of the same submap with the same
// settings: its train.json plus the point count and log-std quantiles), and broken archives.

import { after, before, describe, test } from 'node:test';
import assert from 'node:assert/strict';
import { existsSync, mkdtempSync, readFileSync, rmSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { spawnSync } from 'node:child_process';
import { join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';
import { serve } from './viewer.mjs';

const ROOT = resolve(fileURLToPath(new URL('../..', import.meta.url)));
const FIXTURES = process.env.SILVR_STUDIO_FIXTURES || join(ROOT, 'target', 'studio-fixtures');
/** The native binary the cargo tests built (a browser checkpoint must resume there). */
const SILVR = join(process.env.CARGO_TARGET_DIR || join(ROOT, 'target'), 'debug', 'silvr');
const STARTUP_TIMEOUT_MS = 120_000;
const RUN_TIMEOUT_MS = 600_000;

/** The run of tests/tests/submap.rs (native reference), as the studio's link presets it. */
const qualityRun = (steps) =>
  `steps=${steps}&rays=256&model=tiny&downscale=2&export=4096&uncertainty=2&view-every=50&views=8&mode=silvr`;
/** The quality run, the same in both browsers (tests/tests/submap.rs runs it natively: micro-native.json). */
const QUALITY_STEPS = 150;
const BROWSER_RUN = qualityRun(QUALITY_STEPS);
/** Runs that test a path (faults, resuming), not quality: short, and nothing after training but the checkpoint. */
const PATH_RUN = 'rays=256&model=tiny&downscale=2&export=0&uncertainty=0&view-every=0&views=0&mode=silvr';
// Tolerances of the quality run against the native WGSL run, ~4× the worst disagreement measured
// (2026-12-04, 2-core CPU machine, wgpu on Mesa lavapipe natively): the browser runs are not bit-exact (nor
// are native runs of the same seed), so the fixture that tests/tests/submap.rs writes is one draw of a
// native run. Measured |browser − native| over 6 runs each in Chromium 156 / SwiftShader and Firefox ESR 153 /
// lavapipe, and |native − native| over 3 more native runs (the fixture is re-made on every CI run):
//                    Chromium     Firefox      native       worst     tolerance
//   held-out PSNR    ≤ 0.0016 dB  ≤ 0.0012 dB  ≤ 0.0017 dB  0.0017    0.008 dB
//   exported points  ≤ 0.61 %     ≤ 1.09 %     ≤ 1.34 %     1.34 %    5 % then; 20 % since (below)
//   log10-std Q1–Q3  ≤ 0.034      ≤ 0.027      ≤ 0.046      0.046     0.15 decades
// A run 10 steps short (140 of 150) misses all three (0.060 dB, 29 %, 0.28 decades); the old bounds
// (0.5 dB, 25 %, 0.6 decades) passed its PSNR and quartiles. The quartiles compare two read-outs of the
// same definition, so a change of the read-out's units (both sides) leaves their agreement as it is.
// Also measured, against the same bounds: the fox run (vision-only) agrees within 0.0001 dB in both
// browsers, and the native checkpoint continued 10 steps in the browser gains 0.009 dB.
/** Held-out PSNR of the browser run within this of the native WGSL run (dB). */
const PSNR_TOLERANCE_DB = 0.008;
/** Exported points within this fraction of the native count (accumulation ≥ 0.98 is a sharp cut). */
// Re-measured after the metric uncertainty (held-out lidar returns; 2026-12-04, session 19): the export
// count spreads more than before: native 188, 193, 196 over three runs of one seed; against the 188 fixture
// Chromium 209 and 214 (+11, +14 %), Firefox 216 and 187 (+15, −0.5 %), held-out PSNR within 0.0003 dB every
// time. 20 % holds that spread and still fails the 10-steps-short run (29 %).
// The σ quartiles are all 0.00 decades on both sides at this budget: the 150-step field's held-out lidar
// residual is ~1.2 m, so the calibrated σ of every point sits at the 1 m prior (correctly); the check then
// guards only that the browser reports the same (finite, prior) σ.
const POINTS_TOLERANCE = 0.2;
/** log10-std quartiles (25, 50, 75 %) within this many decades of the native run's. */
const QUANTILE_TOLERANCE = 0.15;
/** The uncertainty pass's Fisher totals (colour, depth) within these many decades of the native run's. */
// Measured 2026-12-04 (session 22; 3 runs in each browser against one native fixture, 4 native runs):
// |log10(browser / native)| colour ≤ 0.067 (Chromium 0.029–0.064, Firefox 0.008–0.067), depth ≤ 0.117; native
// runs of one seed spread 0.013 (colour) and 0.13 (depth: 303 to 408) decades, and CI re-makes the fixture,
// so depth can meet a browser run 0.18 decades away. Bounds: ~2× those. At 150 steps the calibrated σ, the
// factor (at its 1e8 cap) and the raw σ's medians (0.90–0.95 m against the 1 m prior) all sit near the
// prior; the totals are what follows the Fisher the worker accumulated.
const FISHER_TOLERANCE = [0.15, 0.3];
/** The raw σ's median on held-out returns (colour, depth, combined) within these many decades: measured
 * |log10(browser / native)| ≤ 0.0001 (colour, at the prior), ≤ 0.022 (depth, combined; native runs spread
 * 0.033). A worker whose grid differs from the native one (16 cells a side) keeps the totals within 0.03
 * decades but moves these by 0.10 (colour) and 1.24 decades (depth): it fails. */
const RAW_SIGMA_TOLERANCE = [0.02, 0.1, 0.1];

export function trainSuite(driver) {
  const ready = existsSync(join(ROOT, 'dist', 'index.html')) && existsSync(join(FIXTURES, 'micro.tar')) && existsSync(SILVR);
  describe(`studio training in ${driver.name}`, { timeout: 2 * RUN_TIMEOUT_MS }, () => {
    let server, browser;
    before(async () => {
      if (!ready) {
        throw new Error(
          `needs dist/ (trunk build), ${FIXTURES}/micro.tar (left by the native test tests/tests/submap.rs ` +
            `when SILVR_STUDIO_FIXTURES is set) and ${SILVR}: run scripts/test.sh`,
        );
      }
      server = await serve();
      browser = await driver.launch();
    });
    after(async () => {
      await driver.close(browser);
      await server?.close();
    });

    const open = async (query) => {
      const { page, log } = await driver.newPage(browser);
      await driver.goto(page, `${server.base}/?${query}`);
      // Long tasks on the main thread (Chromium has the Long Tasks API; Firefox does not).
      await driver.evaluate(page, () => {
        window.__long = { supported: false, tasks: [] };
        try {
          new PerformanceObserver((l) => {
            for (const e of l.getEntries()) window.__long.tasks.push({ start: e.startTime, ms: e.duration });
          }).observe({ type: 'longtask', buffered: true });
          window.__long.supported = (PerformanceObserver.supportedEntryTypes || []).includes('longtask');
        } catch {}
      });
      await driver.waitFor(page, () => document.body.dataset.state !== 'loading', null, STARTUP_TIMEOUT_MS);
      const state = await driver.evaluate(page, () => document.body.dataset.state);
      assert.equal(state, 'ready', `studio state ${state}\n${log.join('\n')}`);
      return { page, log };
    };
    const status = (page) => driver.evaluate(page, () => ({ ...document.querySelector('#train-status').dataset }));
    const waitState = (page, states, timeout = RUN_TIMEOUT_MS) =>
      driver.waitFor(page, (states) => states.includes(document.querySelector('#train-status').dataset.state), states, timeout);

    test('a packed submap trains in the worker as natively: loss falls, pause/resume, held-out view, points and uncertainty, no long tasks', async () => {
      const steps = QUALITY_STEPS;
      const native = JSON.parse(readFileSync(join(FIXTURES, 'micro-native.json'), 'utf8'));
      assert.equal(native.steps, steps);
      const { page, log } = await open(`train=${encodeURIComponent('/data/micro.tar')}&${qualityRun(steps)}`);
      await driver.waitFor(page, () => Number(document.querySelector('#train-status').dataset.step || 0) >= 1, null, RUN_TIMEOUT_MS);
      const t0 = await driver.evaluate(page, () => performance.now());
      const wall0 = Date.now();
      const adapter = await driver.evaluate(page, () => document.querySelector('#adapter').dataset.name);

      // Pause: the step counter stops; resume: it moves on.
      await driver.waitFor(page, () => Number(document.querySelector('#train-status').dataset.step) >= 20, null, RUN_TIMEOUT_MS);
      await driver.evaluate(page, () => document.querySelector('#train-pause').click());
      await waitState(page, ['paused'], 60_000);
      const paused = Number((await status(page)).step);
      await new Promise((r) => setTimeout(r, 2500));
      assert.equal(Number((await status(page)).step), paused, 'a paused run took steps');
      await driver.evaluate(page, () => document.querySelector('#train-pause').click());
      await driver.waitFor(page, (s) => Number(document.querySelector('#train-status').dataset.step) > s, paused, 60_000);

      // The held-out view beside its photo, rendered at step 50.
      await driver.waitFor(page, () => document.querySelector('#train-render').dataset.step === '50', null, RUN_TIMEOUT_MS);
      assert.equal(await driver.evaluate(page, () => document.querySelector('#train-photo').hidden), false);

      await waitState(page, ['done', 'failed']);
      const t1 = await driver.evaluate(page, () => performance.now());
      const s = await status(page);
      assert.equal(s.state, 'done', `${await driver.evaluate(page, () => document.querySelector('#train-error').textContent)}\n${log.join('\n')}`);
      assert.equal(s.step, String(steps));
      const start = Number(s.lossStart);
      const recent = Number(s.lossRecent);
      assert.ok(recent < 0.6 * start, `loss fell from ${start} (first ten steps) to only ${recent} (last ten)`);

      const r = JSON.parse(await driver.evaluate(page, () => document.querySelector('#train-result').dataset.result));
      const nativePsnr = native.heldout_psnr_mean;
      console.log(
        `${driver.name} (${adapter}): ${steps} steps in ${r.train_s.toFixed(0)} s of training ` +
          `(${((Date.now() - wall0) / 1000).toFixed(0)} s wall), ${r.rays_per_s.toFixed(0)} rays/s ` +
          `(native WGSL ${native.train_rays_per_s.toFixed(0)}); held-out PSNR ${r.heldout_psnr.toFixed(2)} dB ` +
          `(native ${nativePsnr.toFixed(2)}); ${r.points} points (native ${native.points_count}); log-std quantiles ` +
          `${r.log_std_quantiles.map((q) => q.toFixed(2)).join(' ')} (native ${native.log_std_quantiles.map((q) => q.toFixed(2)).join(' ')})`,
      );
      // The agreement the tolerances below are set from.
      const dPsnr = Math.abs(r.heldout_psnr - nativePsnr);
      const dPoints = Math.abs(r.points - native.points_count) / native.points_count;
      const dQuartiles = [1, 2, 3].map((k) => Math.abs(r.log_std_quantiles[k] - native.log_std_quantiles[k]));
      console.log(
        `${driver.name} vs native: |Δ PSNR| ${dPsnr.toFixed(4)} dB (tolerance ${PSNR_TOLERANCE_DB}), |Δ points| ` +
          `${(100 * dPoints).toFixed(2)} % (tolerance ${100 * POINTS_TOLERANCE} %), |Δ log-std quartiles| ` +
          `${dQuartiles.map((d) => d.toFixed(4)).join(' ')} decades (tolerance ${QUANTILE_TOLERANCE})`,
      );
      assert.equal(r.backend, 'wgpu');
      assert.ok(Math.abs(r.heldout_psnr - nativePsnr) <= PSNR_TOLERANCE_DB, `held-out PSNR ${r.heldout_psnr} vs native ${nativePsnr}`);
      assert.equal(r.held_out_views, native.heldout.length);
      assert.ok(Math.abs(r.points - native.points_count) <= POINTS_TOLERANCE * native.points_count, `${r.points} points vs native ${native.points_count}`);
      assert.equal(r.log_std_quantiles.length, 5);
      for (const k of [1, 2, 3]) {
        const d = Math.abs(r.log_std_quantiles[k] - native.log_std_quantiles[k]);
        assert.ok(d <= QUANTILE_TOLERANCE, `log-std quantile ${k}: ${r.log_std_quantiles[k]} vs native ${native.log_std_quantiles[k]}`);
      }
      // The uncertainty pass itself. At this budget the calibrated σ above all read the prior, and so does
      // the calibration factor (at its cap: the held-out residuals exceed the prior); what follows the Fisher
      // the worker accumulated is its total, colour and depth (Σ of the diagonals over every cell).
      const nb = native.uncertainty_brief;
      assert.ok(nb && r.uncertainty, `uncertainty brief: browser ${JSON.stringify(r.uncertainty)}, native ${JSON.stringify(nb)}`);
      const dFisher = [0, 1].map((k) => Math.abs(Math.log10(r.uncertainty.fisher_totals[k] / nb.fisher_totals[k])));
      console.log(
        `${driver.name} vs native: Fisher totals (colour, depth) ${r.uncertainty.fisher_totals.map((v) => v.toFixed(1))} vs ` +
          `${nb.fisher_totals.map((v) => v.toFixed(1))} (|Δ| ${dFisher.map((d) => d.toFixed(3))} decades, tolerance ` +
          `${FISHER_TOLERANCE} decades); raw median σ ${r.uncertainty.raw_median_sigma_m.map((v) => v?.toFixed(4))} ` +
          `vs ${nb.raw_median_sigma_m.map((v) => v?.toFixed(4))} m; factors ${r.uncertainty.factors.map((v) => v.toExponential(2))} ` +
          `vs ${nb.factors.map((v) => v.toExponential(2))}`,
      );
      for (const k of [0, 1]) {
        assert.ok(dFisher[k] <= FISHER_TOLERANCE[k], `Fisher total ${k}: ${r.uncertainty.fisher_totals[k]} vs native ${nb.fisher_totals[k]}`);
      }
      // How the Fisher spreads over the cells (a different grid keeps the totals but not this).
      for (const k of [0, 1, 2]) {
        const d = Math.abs(Math.log10(r.uncertainty.raw_median_sigma_m[k] / nb.raw_median_sigma_m[k]));
        assert.ok(d <= RAW_SIGMA_TOLERANCE[k], `raw median σ of read-out ${k}: ${r.uncertainty.raw_median_sigma_m[k]} vs native ${nb.raw_median_sigma_m[k]} m`);
      }
      // The calibration: since the ray's spread is part of σ (2026-12-05) the fit has two factors per read-out
      // (k on the Laplace σ, a on the spread) that trade against each other on a grid of a, so a tiny
      // difference in the held-out renders can move both; what they make of the held-out returns, the
      // calibrated median σ there, is what is compared.
      console.log(
        `${driver.name} vs native: calibrated median σ on held-out returns ${r.uncertainty.calibrated_median_sigma_m.map((v) => v?.toFixed(4))} ` +
          `vs ${nb.calibrated_median_sigma_m.map((v) => v?.toFixed(4))} m`,
      );
      for (const k of [0, 1, 2]) {
        const d = Math.abs(Math.log10(r.uncertainty.calibrated_median_sigma_m[k] / nb.calibrated_median_sigma_m[k]));
        assert.ok(d <= QUANTILE_TOLERANCE, `calibrated median σ of read-out ${k}: ${r.uncertainty.calibrated_median_sigma_m[k]} vs native ${nb.calibrated_median_sigma_m[k]} m`);
      }
      assert.ok(r.kept > 0 && r.kept <= r.points);
      assert.ok(r.outputs.includes('checkpoint.ckpt') && r.outputs.includes('points_filtered.ply'));
      // The uncertainty image of the held-out view is shown at the end.
      assert.equal(await driver.evaluate(page, () => document.querySelector('#train-uncertainty').hidden), false);
      // The trained points are a layer of the view.
      await driver.waitFor(page, () => [...document.querySelectorAll('#layers li')].some((l) => l.textContent.includes('points.ply')), null, 60_000);
      // Outputs download; the browser's checkpoint continues natively (one format both ways).
      await driver.evaluate(page, () => {
        window.__blobs = [];
        const create = URL.createObjectURL;
        URL.createObjectURL = (b) => {
          window.__blobs.push(b);
          return create.call(URL, b);
        };
      });
      for (const name of ['points.ply', 'checkpoint.ckpt']) {
        await driver.evaluate(page, (name) => document.querySelector(`#train-result button[data-output="${name}"]`).click(), name);
        await driver.waitFor(page, (name) => [...document.querySelectorAll('#view-messages li')].some((l) => l.textContent.includes(`Downloaded ${name}`)), name, 60_000);
      }
      const ckpt = Buffer.from(
        await driver.evaluate(page, async () => {
          const bytes = new Uint8Array(await window.__blobs[window.__blobs.length - 1].arrayBuffer());
          let s = '';
          for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
          return btoa(s);
        }),
        'base64',
      );
      const tmp = mkdtempSync(join(tmpdir(), 'silvr-browser-ckpt-'));
      writeFileSync(join(tmp, 'browser.ckpt'), ckpt);
      const resumed = spawnSync(SILVR, [
        'train', join(FIXTURES, 'micro.tar'), '--resume', join(tmp, 'browser.ckpt'), '--steps', String(steps + 10), '--rays', '256',
        '--model', 'tiny', '--downscale', '2', '--backend', 'wgpu', '--export-rays', '0', '--render-views', '0',
        '--out', join(tmp, 'native'),
      ], { encoding: 'utf8', env: { ...process.env, WGPU_BACKEND: process.env.WGPU_BACKEND || 'vulkan' } });
      assert.equal(resumed.status, 0, resumed.stderr);
      assert.match(resumed.stderr, new RegExp(`resumed .*browser\\.ckpt at step ${steps}\\b`));
      assert.equal(JSON.parse(readFileSync(join(tmp, 'native', 'train.json'), 'utf8')).steps, steps + 10);
      rmSync(tmp, { recursive: true, force: true });

      // The main thread stayed free while the worker trained.
      const long = await driver.evaluate(page, () => window.__long);
      if (long.supported) {
        const during = long.tasks.filter((t) => t.start >= t0 && t.start <= t1);
        console.log(`${driver.name}: ${during.length} main-thread long tasks during training (${during.map((t) => t.ms.toFixed(0)).join(', ')} ms)`);
        assert.deepEqual(during.filter((t) => t.ms > 50), [], 'long tasks over 50 ms while training');
      } else {
        console.log(`${driver.name}: no Long Tasks API; main-thread responsiveness is checked in Chromium`);
      }
      const errors = log.filter((l) => l.startsWith('[pageerror]'));
      assert.deepEqual(errors, [], log.join('\n'));
      await page.close();
    });

    test('a reload mid-training resumes from the checkpoint in browser storage; a native checkpoint continues in the browser', async () => {
      const native = JSON.parse(readFileSync(join(FIXTURES, 'micro-native.json'), 'utf8'));
      const query = `train=${encodeURIComponent('/data/micro.tar')}&steps=80&${PATH_RUN}&checkpoint-every=20`;
      const { page, log } = await open(query);
      await driver.waitFor(page, () => Number(document.querySelector('#train-status').dataset.savedStep || 0) >= 20, null, RUN_TIMEOUT_MS);
      const before = await status(page);
      const saved = Number(before.savedStep);
      // Reload: the saved run is offered (and the link does not start a new one); resume it.
      await driver.goto(page, `${server.base}/?${query}`);
      await driver.waitFor(page, () => !document.querySelector('#train-resume').hidden, null, STARTUP_TIMEOUT_MS);
      assert.equal(await driver.evaluate(page, () => document.querySelector('#train-resume').dataset.step), String(saved));
      await driver.evaluate(page, () => document.querySelector('#train-resume').click());
      await driver.waitFor(page, (s) => Number(document.querySelector('#train-status').dataset.step || 0) >= s + 10, saved, RUN_TIMEOUT_MS);
      const after = await status(page);
      assert.equal(Number(after.firstStep), saved + 1, 'the resumed run continues at the saved step');
      assert.ok(
        Number(after.lossRecent) < 0.8 * Number(before.lossStart),
        `the resumed run's loss ${after.lossRecent} is not below the run's start ${before.lossStart}`,
      );
      // Stop: the run finishes and is no longer offered for resuming.
      await driver.evaluate(page, () => document.querySelector('#train-stop').click());
      await waitState(page, ['done', 'failed']);
      assert.equal((await status(page)).state, 'done', await driver.evaluate(page, () => document.querySelector('#train-error').textContent));

      // The native run's checkpoint (150 steps on the same submap) continues here to step 160.
      const { page: p2, log: log2 } = await open(BROWSER_RUN.replace('steps=150', 'steps=160').replace('export=4096', 'export=0').replace('uncertainty=2', 'uncertainty=0'));
      await driver.upload(p2, '#train-file', join(FIXTURES, 'micro.tar'));
      await driver.upload(p2, '#train-checkpoint', join(FIXTURES, 'micro-native.ckpt'));
      await driver.waitFor(p2, () => !document.querySelector('#train-start').disabled, null, 30_000);
      await driver.evaluate(p2, () => document.querySelector('#train-start').click());
      await waitState(p2, ['done', 'failed']);
      const s2 = await status(p2);
      assert.equal(s2.state, 'done', await driver.evaluate(p2, () => document.querySelector('#train-error').textContent));
      assert.equal(s2.firstStep, '151');
      const r = JSON.parse(await driver.evaluate(p2, () => document.querySelector('#train-result').dataset.result));
      assert.equal(r.steps, 160);
      // Ten more steps from the native field: as good as the native run, within the runs' noise.
      assert.ok(r.heldout_psnr > native.heldout_psnr_mean - PSNR_TOLERANCE_DB, `${r.heldout_psnr} dB after continuing the native ${native.heldout_psnr_mean} dB`);
      console.log(`${driver.name}: resumed at step ${saved + 1} after a reload; the native checkpoint continued to step 160: held-out PSNR ${r.heldout_psnr.toFixed(4)} dB (native at 150: ${native.heldout_psnr_mean.toFixed(4)})`);
      for (const l of [log, log2]) {
        assert.deepEqual(l.filter((x) => x.startsWith('[pageerror]')), [], l.join('\n'));
      }
      await page.close();
      await p2.close();
    });

    test('a lost GPU device mid-training: a message, a new device, the run goes on from its checkpoint', async () => {
      const { page, log } = await open(`train=${encodeURIComponent('/data/micro.tar')}&steps=40&${PATH_RUN}&checkpoint-every=10`);
      await driver.waitFor(page, () => Number(document.querySelector('#train-status').dataset.savedStep || 0) >= 10, null, RUN_TIMEOUT_MS);
      const saved = Number((await status(page)).savedStep);
      await driver.evaluate(page, () => document.querySelector('#view').dispatchEvent(new CustomEvent('silvr-lose-device')));
      await driver.waitFor(page, () => /device was lost/.test(document.querySelector('#train-error').textContent), null, 120_000);
      const message = await driver.evaluate(page, () => document.querySelector('#train-error').textContent);
      assert.match(message, /goes on on a new device from the checkpoint at step \d+/);
      const from = Number(message.match(/checkpoint at step (\d+)/)[1]);
      assert.ok(from >= saved, `resumed from step ${from}, the page had seen a save at ${saved}`);
      await waitState(page, ['done', 'failed']);
      const s = await status(page);
      assert.equal(s.state, 'done', await driver.evaluate(page, () => document.querySelector('#train-error').textContent));
      assert.equal(Number(s.firstStep), from + 1, 'the chart restarts at the checkpoint');
      assert.equal(s.step, '40');
      console.log(`${driver.name}: device lost after step ${saved}+; resumed from the checkpoint at step ${from} on a new device and finished`);
      assert.deepEqual(log.filter((x) => x.startsWith('[pageerror]')), [], log.join('\n'));
      await page.close();
    });

    test('a worker crash mid-training: reported, a new worker started, the saved run resumed', async () => {
      const { page, log } = await open(`train=${encodeURIComponent('/data/micro.tar')}&steps=40&${PATH_RUN}&checkpoint-every=10`);
      await driver.waitFor(page, () => Number(document.querySelector('#train-status').dataset.savedStep || 0) >= 10, null, RUN_TIMEOUT_MS);
      await driver.evaluate(page, () => document.dispatchEvent(new CustomEvent('silvr-debug-panic')));
      await driver.waitFor(page, () => document.querySelector('#error').dataset.restarts === '1', null, 60_000);
      assert.match(await driver.evaluate(page, () => document.querySelector('#error').textContent), /crashed[\s\S]*new worker was started/i);
      await driver.waitFor(page, () => document.body.dataset.state === 'ready', null, STARTUP_TIMEOUT_MS);
      await driver.waitFor(page, () => !document.querySelector('#train-resume').hidden, null, 60_000);
      const from = Number(await driver.evaluate(page, () => document.querySelector('#train-resume').dataset.step));
      assert.ok(from >= 10, `the saved run is at step ${from}`);
      await driver.evaluate(page, () => document.querySelector('#train-resume').click());
      await waitState(page, ['done', 'failed']);
      const s = await status(page);
      assert.equal(s.state, 'done', await driver.evaluate(page, () => document.querySelector('#train-error').textContent));
      assert.equal(Number(s.firstStep), from + 1);
      assert.equal(s.step, '40');
      // The view lives on in the new worker: its kernel check ran and passed.
      assert.equal(await driver.evaluate(page, () => document.querySelector('#projection').dataset.passed), 'true');
      console.log(`${driver.name}: the worker crashed after a checkpoint at step ${from}; a new worker resumed it and finished`);
      // A readback in flight when the worker panics is rejected as the dead worker goes (Firefox reports
      // the unhandled "AbortError: Buffer unmapped" to the page, depending on timing): a consequence of the
      // crash this test causes, not an error of the studio's.
      const errors = log.filter((x) => x.startsWith('[pageerror]') && !x.includes('AbortError: Buffer unmapped'));
      assert.deepEqual(errors, [], log.join('\n'));
      await page.close();
    });

    test('a nerfstudio capture (camera only) trains vision-only in the worker', { skip: (!existsSync(join(FIXTURES, 'fox.tar')) && process.env.SILVR_REQUIRE_DATA !== '1' && 'no fox.tar fixture (../shared/data/real/fox absent)') }, async () => {
      if (!existsSync(join(FIXTURES, 'fox.tar'))) throw new Error(`${join(FIXTURES, 'fox.tar')} missing with SILVR_REQUIRE_DATA=1 (tests/tests/submap.rs writes it from ../shared/data/real/fox)`);
      const native = JSON.parse(readFileSync(join(FIXTURES, 'fox-native.json'), 'utf8'));
      // Mode silvr asked for: a capture without lidar trains vision-only all the same.
      const run = 'steps=40&rays=256&model=tiny&downscale=8&export=0&uncertainty=0&view-every=0&views=1&mode=silvr';
      const { page, log } = await open(`train=${encodeURIComponent('/data/fox.tar')}&${run}`);
      await waitState(page, ['done', 'failed']);
      const s = await status(page);
      assert.equal(s.state, 'done', await driver.evaluate(page, () => document.querySelector('#train-error').textContent));
      const r = JSON.parse(await driver.evaluate(page, () => document.querySelector('#train-result').dataset.result));
      console.log(`${driver.name}: fox (camera only) trained vision-only: held-out PSNR ${r.heldout_psnr.toFixed(4)} dB (native ${native.heldout_psnr_mean.toFixed(4)})`);
      assert.ok(Math.abs(r.heldout_psnr - native.heldout_psnr_mean) <= PSNR_TOLERANCE_DB, `${r.heldout_psnr} vs native ${native.heldout_psnr_mean}`);
      assert.equal(r.mode, 'vision');
      assert.deepEqual(log.filter((x) => x.startsWith('[pageerror]')), [], log.join('\n'));
      await page.close();
    });

    test('a submap dropped on the training card is chosen for training', async () => {
      const { page, log } = await open('');
      await driver.evaluate(page, async () => {
        const blob = await (await fetch('/data/micro.tar')).blob();
        const dt = new DataTransfer();
        dt.items.add(new File([blob], 'micro.tar', { type: 'application/x-tar' }));
        const card = document.querySelector('#train-card');
        card.dispatchEvent(new DragEvent('dragover', { dataTransfer: dt, bubbles: true, cancelable: true }));
        card.dispatchEvent(new DragEvent('drop', { dataTransfer: dt, bubbles: true, cancelable: true }));
      });
      await waitState(page, ['ready', 'failed'], 30_000);
      assert.match(await driver.evaluate(page, () => document.querySelector('#train-status').textContent), /Chosen: micro\.tar/);
      assert.equal(await driver.evaluate(page, () => document.querySelector('#train-start').disabled), false);
      assert.deepEqual(log.filter((x) => x.startsWith('[pageerror]')), [], log.join('\n'));
      await page.close();
    });

    test('a dataset folder chosen with the folder input trains, its files read by their relative paths', { skip: !driver.folderUpload && 'WebDriver BiDi in Firefox cannot choose a folder for an input (input.setFiles: NS_ERROR_FILE_IS_DIRECTORY); the same page code runs in Chromium' }, async () => {
      const dir = mkdtempSync(join(tmpdir(), 'silvr-folder-'));
      const micro = join(dir, 'micro');
      spawnSync('mkdir', [micro]);
      const untar = spawnSync('tar', ['xf', join(FIXTURES, 'micro.tar'), '-C', micro], { encoding: 'utf8' });
      assert.equal(untar.status, 0, untar.stderr);
      const { page, log } = await open('steps=3&rays=256&model=tiny&downscale=2&export=0&uncertainty=0&view-every=0&views=0&mode=silvr');
      await driver.upload(page, '#train-folder', micro);
      await waitState(page, ['ready', 'failed'], 30_000);
      assert.match(await driver.evaluate(page, () => document.querySelector('#train-status').textContent), /Chosen: micro \(\d+ files\)/);
      await driver.evaluate(page, () => document.querySelector('#train-start').click());
      await waitState(page, ['done', 'failed']);
      const s = await status(page);
      assert.equal(s.state, 'done', await driver.evaluate(page, () => document.querySelector('#train-error').textContent));
      assert.equal(s.step, '3');
      assert.deepEqual(log.filter((x) => x.startsWith('[pageerror]')), [], log.join('\n'));
      await page.close();
      rmSync(dir, { recursive: true, force: true });
    });

    test('a batch too large for the adapter names the limit and the setting to change', async () => {
      const run = PATH_RUN.replace('rays=256', 'rays=1048576');
      const { page, log } = await open(`train=${encodeURIComponent('/data/micro.tar')}&steps=10&${run}`);
      await waitState(page, ['failed', 'done'], 300_000);
      const error = await driver.evaluate(page, () => document.querySelector('#train-error').textContent);
      assert.equal((await status(page)).state, 'failed', error);
      assert.match(error, /max_storage_buffer_binding_size/);
      assert.match(error, /fewer rays per batch than 1048576/);
      assert.equal(await driver.evaluate(page, () => document.body.dataset.state), 'ready');
      assert.deepEqual(log.filter((x) => x.startsWith('[pageerror]')), [], log.join('\n'));
      await page.close();
    });

    for (const [file, expect] of [
      ['corrupt-image.tar', /images\/cam_left\/00003\.png.*(cannot read image|not a readable)/],
      ['no-transforms.tar', /no-transforms\.tar.*no transforms\.json/],
      ['missing-lidar.tar', /lidar_depth\/cam_front\/00002\.png.*missing/],
      ['not.ply', /not\.ply.*(tar|archive)/],
    ]) {
      test(`a broken submap (${file}) names the file; the studio keeps working`, async () => {
        const { page, log } = await open(`train=${encodeURIComponent(`/data/${file}`)}&${BROWSER_RUN}`);
        await waitState(page, ['failed', 'done'], 120_000);
        const s = await status(page);
        const error = await driver.evaluate(page, () => document.querySelector('#train-error').textContent);
        assert.equal(s.state, 'failed', error);
        assert.match(error, expect);
        assert.equal(await driver.evaluate(page, () => document.body.dataset.state), 'ready');
        // The worker lives on: the kernel self-check runs again and passes.
        await driver.waitFor(page, () => !document.querySelector('#rerun').disabled, null, 60_000);
        await driver.evaluate(page, () => document.querySelector('#rerun').click());
        await driver.waitFor(page, () => document.querySelector('#projection').dataset.runs === '2', null, 120_000);
        assert.equal(await driver.evaluate(page, () => document.querySelector('#projection').dataset.passed), 'true');
        const errors = log.filter((l) => l.startsWith('[pageerror]'));
        assert.deepEqual(errors, [], log.join('\n'));
        await page.close();
      });
    }
  });
}

// End-to-end test of the observer page in a real Chromium against a running `mrptv serve --demo`.
//   node web/tests/e2e.mjs --url http://127.0.0.1:8770/ [--artifacts DIR] [--flat-only]
// Needs Debian's chromium (/usr/bin/chromium, or MRPTV_CHROMIUM) and `npm ci --prefix web`.
// Prints one JSON line of what it measured; exits non-zero with the reason on any failure.
import assert from 'node:assert/strict';
import { mkdirSync, readFileSync, writeFileSync } from 'node:fs';
import { createRequire } from 'node:module';
import { join } from 'node:path';
import { parseArgs } from 'node:util';
import { chromium } from 'playwright-core';

const { values: args } = parseArgs({
  options: {
    url: { type: 'string' },
    artifacts: { type: 'string', default: 'test-artifacts' },
    'flat-only': { type: 'boolean', default: false },
  },
});
assert.ok(args.url, '--url is required');
mkdirSync(args.artifacts, { recursive: true });
const secure = args.url.startsWith('https:');
const require = createRequire(import.meta.url);
const iwerSource = readFileSync(require.resolve('iwer/build/iwer.min.js'), 'utf8');

const browser = await chromium.launch({
  executablePath: process.env.MRPTV_CHROMIUM || '/usr/bin/chromium',
  args: [
    '--no-sandbox',
    // Software WebGL: CI machines have no GPU.
    '--use-angle=swiftshader',
    '--enable-unsafe-swiftshader',
    '--ignore-gpu-blocklist',
    // This machine's network is closed: no calls home.
    '--disable-background-networking',
    '--disable-component-update',
    '--disable-sync',
    '--no-first-run',
  ],
});

const report = { url: args.url, warnings: [] };
let currentPage = null; // screenshotted if a check fails
const poll = async (page, what, predicate, timeoutMs = 20000) => {
  const started = Date.now();
  for (;;) {
    const stats = await page.evaluate(() => window.mrptv?.stats());
    if (stats && predicate(stats)) return stats;
    if (Date.now() - started > timeoutMs) {
      throw new Error(`timed out after ${timeoutMs} ms waiting for ${what}; last stats: ${JSON.stringify(stats)}`);
    }
    await page.waitForTimeout(100);
  }
};

// A software-rendered frame under load can come out blank (a starved or reset GL context):
// arrows must be on screen in some frame within the timeout, and every attempt is reported.
const probeUntil = async (page, what, predicate, timeoutMs = 10000) => {
  const started = Date.now();
  const attempts = [];
  for (;;) {
    const pixels = await page.evaluate(() => window.mrptv.probePixels());
    attempts.push(pixels);
    if (predicate(pixels)) return { ...pixels, attempts: attempts.length };
    if (Date.now() - started > timeoutMs) {
      const stats = await page.evaluate(() => window.mrptv.stats());
      throw new Error(`${what}: no frame passed in ${timeoutMs} ms; probes: ${JSON.stringify(attempts)}; ` +
        `stats: ${JSON.stringify(stats)}; console warnings: ${JSON.stringify(report.warnings)}`);
    }
    await page.waitForTimeout(250);
  }
};

async function openPage(name, { emulateXr }) {
  // The self-signed certificate of `serve --tls` is what the test wants to be served, unverified.
  const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, ignoreHTTPSErrors: secure });
  if (emulateXr) {
    // Meta's WebXR emulation runtime, installed before the page's own scripts run.
    await context.addInitScript(`${iwerSource}
      ;(() => { const device = new IWER.XRDevice(IWER.metaQuest3); device.installRuntime({ forceInstall: true }); window.__iwer = device; })();`);
  }
  const page = await context.newPage();
  currentPage = page;
  const problems = [];
  page.on('console', (m) => {
    if (m.type() === 'error') problems.push(`${name}: console error: ${m.text()}`);
    if (m.type() === 'warning') report.warnings.push(`${name}: ${m.text()}`);
  });
  page.on('pageerror', (e) => problems.push(`${name}: uncaught: ${e.message}`));
  page.on('requestfailed', (r) => problems.push(`${name}: request failed: ${r.url()} ${r.failure()?.errorText}`));
  page.on('response', (r) => {
    if (r.status() >= 400) problems.push(`${name}: HTTP ${r.status()} for ${r.url()}`);
  });
  await page.goto(args.url);
  return { context, page, problems };
}

const hudNumber = async (page, id) => {
  const text = await page.textContent(`#${id}`);
  const n = parseFloat(text);
  assert.ok(Number.isFinite(n), `HUD #${id} shows ${JSON.stringify(text)}, not a number`);
  return n;
};

try {
  // ---- flat view
  {
    const { context, page, problems } = await openPage('flat', { emulateXr: false });
    // WebXR needs a secure context: https, or http on loopback (which this test may use).
    if (secure) assert.equal(await page.evaluate(() => window.isSecureContext), true, 'https is a secure context');
    const first = await poll(page, 'arrows', (s) => s.arrows > 0 && s.latencyMs !== null && s.framesPerSecond > 0);
    await page.waitForTimeout(1500);
    const later = await poll(page, 'newer frames', (s) => s.frameIndex > first.frameIndex);
    assert.ok(later.batchesDrawn > first.batchesDrawn, 'batches keep being drawn');
    assert.notEqual(later.drawChecksum, first.drawChecksum, 'arrows moved');
    assert.equal(later.badBatches, 0, 'every batch decoded');
    assert.equal(later.subscribed, 's1');
    const hud = {
      vectorsPerSecond: await hudNumber(page, 'hud-vectors'),
      framesPerSecond: await hudNumber(page, 'hud-fps'),
      latencyMs: await hudNumber(page, 'hud-latency'),
      dropped: await hudNumber(page, 'hud-dropped'),
    };
    assert.ok(hud.vectorsPerSecond > 0 && hud.framesPerSecond > 0 && hud.latencyMs > 0, `HUD ${JSON.stringify(hud)}`);
    const legend = await page.textContent('#legend');
    assert.match(legend, /speed, m\/s/);
    assert.match(legend, /arrow length = velocity × [0-9.]+ s/);
    // Chromium without an XR device: no buttons offering what cannot work.
    assert.equal(await page.isVisible('#enter-vr'), false, 'Enter VR hidden without WebXR support');
    assert.equal(await page.isVisible('#enter-ar'), false, 'Enter AR hidden without WebXR support');
    assert.equal(await page.isVisible('#xr-hint'), false, 'no https hint on a secure page');
    const pixels = await probeUntil(page, 'arrows on screen', (p) => p.arrowPixels > 500);
    // Pause freezes the picture while data keeps arriving.
    await page.click('#pause');
    // A batch that arrived before the click may still be drawn in the next animation frame.
    await page.waitForTimeout(300);
    const paused = (await page.evaluate(() => window.mrptv.stats())).frameIndex;
    await page.waitForTimeout(600);
    assert.equal((await page.evaluate(() => window.mrptv.stats())).frameIndex, paused, 'paused picture frozen');
    await page.click('#pause');
    await poll(page, 'resume', (s) => s.frameIndex > paused);
    // Refined vectors: the measurement, M frames behind.
    await page.selectOption('#kind', 'refined');
    await poll(page, 'refined arrows', (s) => s.arrows > 0);
    await page.selectOption('#kind', 'causal');
    await page.waitForTimeout(500);
    await page.screenshot({ path: join(args.artifacts, secure ? 'page-https.png' : 'page.png') });
    // Uncertainties asked for and received (uncertain arrows are drawn lighter).
    assert.equal((await page.evaluate(() => window.mrptv.stats())).sigmasSeen, true, 'batches carry sigmas');
    // Field mode: the session's mean-flow field next to the live vectors.
    await page.check('#field');
    const field = await poll(page, 'field arrows', (s) => s.fieldArrows > 0 && s.fieldArrows === s.fieldCells);
    const fieldPixels = await probeUntil(page, 'field and live arrows on screen', (p) => p.arrowPixels > 500);
    assert.match(await page.textContent('#hud-field'), /cells of [0-9.]+ m, [0-9]+ samples/);
    await page.screenshot({ path: join(args.artifacts, secure ? 'page-field-https.png' : 'page-field.png') });
    // Reset: the field starts again from few samples.
    const grown = await poll(page, 'a grown field', (s) => s.fieldSamples > field.fieldSamples);
    await page.click('#reset-field');
    const restarted = await poll(page, 'a field restarted by the reset', (s) => s.fieldSamples < grown.fieldSamples);
    await page.uncheck('#field');
    await poll(page, 'field hidden', (s) => s.fieldArrows === 0);
    report.field = { cells: field.fieldCells, samples: grown.fieldSamples, afterReset: restarted.fieldSamples, pixels: fieldPixels };
    report.flat = { ...(await page.evaluate(() => window.mrptv.stats())), hud, pixels };
    assert.deepEqual(problems, [], 'no console errors, failed requests or HTTP errors');
    await context.close();
  }

  // ---- a server with a viewers' secret: the page without it is told why it sees nothing
  if (new URL(args.url).searchParams.has('token')) {
    const bare = new URL(args.url);
    bare.searchParams.delete('token');
    const context = await browser.newContext({ viewport: { width: 1280, height: 800 }, ignoreHTTPSErrors: secure });
    const page = await context.newPage();
    currentPage = page;
    await page.goto(bare.href);
    await page.waitForFunction(
      () => document.getElementById('message').textContent.includes("needs the viewers' secret"),
      null,
      { timeout: 15000 },
    );
    const refused = await page.evaluate(() => window.mrptv.stats());
    assert.notEqual(refused.connection, 'open', 'no watch connection without the token');
    assert.equal(refused.arrows, 0);
    report.withoutToken = await page.textContent('#message');
    await context.close();
  }

  // ---- immersive, with the WebXR emulation runtime
  if (!args['flat-only']) {
    const { context, page, problems } = await openPage('xr', { emulateXr: true });
    await poll(page, 'arrows', (s) => s.arrows > 0);
    await page.waitForSelector('#enter-vr:not([hidden])', { timeout: 10000 });
    assert.equal(await page.isVisible('#enter-ar'), true, 'the emulated Quest 3 supports immersive-ar');
    await page.click('#enter-vr');
    const entered = await poll(page, 'an immersive session', (s) => s.xrPresenting && s.xrFrames > 0, 10000);
    await page.waitForTimeout(2000);
    const vr = await page.evaluate(() => window.mrptv.stats());
    assert.equal(vr.xrMode, 'immersive-vr');
    assert.equal(vr.xrReferenceSpace, 'local-floor');
    assert.deepEqual(vr.placement.anchor, [0, 1.3, -1.2], 'volume 1.2 m ahead, 1.3 m above the floor');
    // Software rendering on two cores: a slow frame rate, but frames.
    assert.ok(vr.xrFrames - entered.xrFrames >= 10, `XR frames rendered: ${vr.xrFrames - entered.xrFrames} in 2 s`);
    // Polled, not read once: a looping source's first M frames after a restart carry no refined
    // vectors, so one snapshot can land on an empty frame (seen: frame 301, 0 arrows).
    await poll(page, 'arrows that keep updating in XR', (s) => s.arrows > 0 && s.frameIndex > entered.frameIndex, 10000);
    const xrPixels = await probeUntil(page, 'arrows in an XR frame', (p) => p.presenting && p.arrowPixels > 200);
    await page.screenshot({ path: join(args.artifacts, 'xr-vr.png') });
    // In XR the emulator's canvas covers the page: press the (now "Exit VR") button directly.
    await page.$eval('#enter-vr', (b) => b.click());
    await poll(page, 'the end of the session', (s) => !s.xrPresenting, 5000);
    await page.click('#enter-ar');
    const ar = await poll(page, 'an AR session', (s) => s.xrPresenting && s.xrMode === 'immersive-ar', 10000);
    await page.waitForTimeout(500);
    const arLater = await page.evaluate(() => window.mrptv.stats());
    assert.ok(arLater.xrFrames > ar.xrFrames, 'AR frames rendered');
    const arPixels = await probeUntil(page, 'arrows in an AR frame', (p) => p.presenting && p.arrowPixels > 200);
    await page.screenshot({ path: join(args.artifacts, 'xr-ar.png') });
    report.xr = {
      vrFramesIn2s: vr.xrFrames - entered.xrFrames,
      vrPixels: xrPixels,
      arPixels,
      placement: vr.placement,
    };
    assert.deepEqual(problems, [], 'no console errors, failed requests or HTTP errors');
    await context.close();
  }
  writeFileSync(join(args.artifacts, secure ? 'report-https.json' : 'report.json'), JSON.stringify(report, null, 2));
  console.log(JSON.stringify(report));
} catch (e) {
  console.error(`e2e failed: ${e.stack ?? e}`);
  process.exitCode = 1;
  if (currentPage) {
    const shot = join(args.artifacts, `failure${secure ? '-https' : ''}.png`);
    try {
      console.error(`stats at failure: ${JSON.stringify(await currentPage.evaluate(() => window.mrptv?.stats()))}`);
      await currentPage.screenshot({ path: shot });
      console.error(`screenshot: ${shot}`);
    } catch (shotError) {
      console.error(`no failure screenshot: ${shotError.message}`);
    }
  }
} finally {
  await browser.close();
}

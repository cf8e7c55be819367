// Browser check of the slag-edge page (run by tests/tests/web_viewer.rs, or by hand):
//   node edge/web/e2e.mjs http://127.0.0.1:PORT OUT_DIR "prompt" [...more prompts]
// Starts headless Chromium (software WebGL through SwiftShader), opens the page, waits until it
// says its handlers are attached (data-ready), types each prompt, waits until the page says the
// splat is rendered (every wait bounded: 30 s to ready, 45 s per render), and saves OUT_DIR/<n>-<prompt>.png
// plus OUT_DIR/result.json ({prompt, matches, objects, state, status, png}). Exit 1 on a page error.
import { chromium } from 'playwright-core';
import { mkdirSync, writeFileSync, mkdtempSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join } from 'node:path';

const [url, out, ...prompts] = process.argv.slice(2);
if (!url || !out || prompts.length === 0) {
  console.error('usage: node e2e.mjs URL OUT_DIR PROMPT...');
  process.exit(2);
}
mkdirSync(out, { recursive: true });
const exe = process.env.CHROMIUM || '/usr/bin/chromium';
const userDataDir = mkdtempSync(join(tmpdir(), 'slag-chromium-'));
const ctx = await chromium.launchPersistentContext(userDataDir, {
  executablePath: exe,
  headless: true,
  viewport: { width: 640, height: 480 },
  args: [
    '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
    '--disable-background-networking', '--disable-component-update', '--disable-sync',
    '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--ignore-gpu-blocklist',
  ],
});
const page = ctx.pages()[0] || (await ctx.newPage());
const logs = [];
page.on('console', (m) => logs.push(`${m.type()}: ${m.text()}`));
page.on('pageerror', (e) => logs.push(`pageerror: ${e.message}`));
const results = [];
let failed = false;
// Every wait is bounded well under a minute and says what it waited for when it expires.
const READY_MS = 30000;  // page load + the viewer module's import
const RENDER_MS = 45000; // one answer: /query.ply, parsing, the sort worker, six frames
async function waitFor(what, fn, ms) {
  try {
    await page.waitForFunction(fn, null, { timeout: ms, polling: 200 });
  } catch (e) {
    const state = await page.evaluate(() => document.body.dataset.state).catch(() => '?');
    const st = await page.textContent('#status').catch(() => '?');
    throw new Error(`timed out after ${ms / 1000} s waiting for ${what} (page state ${state}, status "${st}")`);
  }
}
try {
  await page.goto(url, { waitUntil: 'load', timeout: READY_MS });
  await waitFor('the page to attach its handlers (data-ready)', () => document.body.dataset.ready === '1', READY_MS);
  for (const [i, prompt] of prompts.entries()) {
    await page.fill('#text', prompt, { timeout: READY_MS });
    await page.click('#go', { timeout: READY_MS });
    await waitFor(`the answer to "${prompt}" to render`,
      () => ['rendered', 'error', 'no-viewer'].includes(document.body.dataset.state), RENDER_MS);
    // Give the sort worker and SwiftShader a moment for the final frames.
    await page.waitForTimeout(1500);
    const state = await page.evaluate(() => document.body.dataset.state);
    const matches = Number(await page.evaluate(() => document.body.dataset.matches || '0'));
    const objects = Number(await page.evaluate(() => document.body.dataset.objects || '0'));
    const status = await page.textContent('#status');
    const png = join(out, `${i}-${prompt.replace(/[^A-Za-z0-9_-]/g, '_')}.png`);
    await page.screenshot({ path: png, timeout: READY_MS });
    results.push({ prompt, matches, objects, state, status, png });
    if (state !== 'rendered') failed = true;
    // Reset the state so the next prompt waits for its own render.
    await page.evaluate(() => { document.body.dataset.state = 'idle'; });
  }
} catch (e) {
  logs.push(`e2e: ${e.message}`);
  try {
    logs.push(`page state ${await page.evaluate(() => document.body.dataset.state)}: ${await page.textContent('#status')}`);
    await page.screenshot({ path: join(out, 'failure.png') });
  } catch (_) { /* page gone */ }
  failed = true;
} finally {
  writeFileSync(join(out, 'result.json'), JSON.stringify({ results, logs }, null, 2));
  await ctx.close();
  rmSync(userDataDir, { recursive: true, force: true });
}
console.log(JSON.stringify({ results, logs: logs.slice(-20) }, null, 2));
process.exit(failed ? 1 : 0);

// The browser side of tests/server/test_viewer_browser.py (and scripts/viewer_screenshots.py): one headless Chromium
// (the Debian package's, driven by playwright-core from node_modules: no browser download) opens each page of a plan,
// waits until the viewer says it is ready (body[data-state] "ready") or failed ("error"), and takes the screenshots
// the plan asks for. One launch for every page.
//
//   node tests/server/viewer_browser.mjs PLAN.json     -> prints one JSON line: {"pages": [...], "launch_s": ...}
//
// PLAN: {"executable": "/usr/bin/chromium", "timeout_ms": 60000, "pages": [{"url", "viewport": [w, h],
//        "keys": ["h"], "script": "JS run in the page after it is ready" | null, "screenshot": "out.png" | null,
//        "selector": "#canvas", "refuse": "a URL pattern answered 422" | null}]}
import { readFileSync } from "node:fs";
import { chromium } from "playwright-core";

const plan = JSON.parse(readFileSync(process.argv[2], "utf8"));
const t0 = Date.now();
// SwiftShader: WebGL2 in software (no GPU here); --enable-unsafe-swiftshader: Chromium refuses it for WebGL otherwise
const browser = await chromium.launch({
  executablePath: plan.executable, headless: true,
  args: ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-sandbox"],
});
const out = { launch_s: (Date.now() - t0) / 1000, pages: [] };
try {
  for (const p of plan.pages) {
    const page = await browser.newPage({ viewport: { width: p.viewport[0], height: p.viewport[1] },
                                         deviceScaleFactor: 1 });
    const consoleLines = [];
    page.on("console", (m) => consoleLines.push(`${m.type()}: ${m.text()}`));
    page.on("pageerror", (e) => consoleLines.push(`pageerror: ${e.message}`));
    if (p.refuse) {                         // answer 422 to these URLs (a server that does not offer them)
      await page.route(new RegExp(p.refuse), (r) => r.fulfill({ status: 422, contentType: "application/json",
        body: JSON.stringify({ error: { code: "invalid", message: "refused by the test", field: "format" } }) }));
    }
    const started = Date.now();
    const result = { url: p.url, console: consoleLines };
    try {
      const resp = await page.goto(p.url, { waitUntil: "load", timeout: plan.timeout_ms });
      result.status = resp ? resp.status() : null;
      await page.waitForFunction(
        () => ["ready", "error"].includes(document.body && document.body.dataset.state) ||
              !!document.querySelector("#error:not([hidden])"),
        null, { timeout: plan.timeout_ms, polling: 100 });
      result.state = await page.evaluate(() => document.body.dataset.state || null);
      result.error = await page.evaluate(() => {
        const e = document.querySelector("#error:not([hidden])");
        return e ? e.textContent : null;
      });
      result.canvas_visible = await page.evaluate(() => {
        const c = document.querySelector("canvas");
        return !!c && c.getBoundingClientRect().width > 0 && getComputedStyle(c).visibility !== "hidden";
      });
      result.viewer = await page.evaluate(() => window.xyzcylViewer ? {
        state: window.xyzcylViewer.state, render_query: window.xyzcylViewer.renderQuery(),
        summary: window.xyzcylViewer.summary(),
        canvas: [document.querySelector("#canvas").width, document.querySelector("#canvas").height],
      } : null);
      result.ready_s = (Date.now() - started) / 1000;
      for (const k of p.keys || []) await page.keyboard.press(k);
      if (p.script) await page.evaluate(p.script);      // a scripted move (window.xyzcylViewer)
      if ((p.keys || []).length || p.script) {          // then the view drawn again (seconds in software WebGL)
        await page.evaluate(() => window.xyzcylViewer && window.xyzcylViewer.settled());
      }
      if (p.screenshot) {
        await page.locator(p.selector || "#canvas").screenshot({ path: p.screenshot, timeout: plan.timeout_ms });
        result.screenshot = p.screenshot;
      }
    } catch (e) {
      result.failure = String(e && e.message ? e.message : e);
    }
    out.pages.push(result);
    await page.close();
  }
} finally {
  await browser.close();
}
out.total_s = (Date.now() - t0) / 1000;
console.log(JSON.stringify(out));

// Drives the f3g player in headless Chromium (puppeteer-core, Debian's chromium): opens
// URL, waits for the page's readiness flag, optionally sets a view and a frame, and writes a
// screenshot and a JSON report (console errors, readiness, frame rate).
//
//   node shoot.mjs URL OUT.png REPORT.json [--view ex,ey,ez,tx,ty,tz,fov,w,h] [--frame F]
//        [--measure SECONDS [--still]] [--slider] [--corrupt-avatar]
//
// `--corrupt-avatar` serves the page a truncated avatar.glb (request interception), to check
// that the page shows the error.
import { launchChromium } from "./chromium.mjs";
import { writeFileSync } from "fs";

const [url, out, reportPath, ...rest] = process.argv.slice(2);
const option = (name) => {
  const i = rest.indexOf(name);
  return i >= 0 ? rest[i + 1] : undefined;
};
const report = { errors: [], ready: false };
const started = Date.now();
const browser = await launchChromium();
try {
  const page = await browser.newPage();
  page.on("console", (m) => { if (m.type() === "error") report.errors.push(m.text()); });
  page.on("pageerror", (e) => report.errors.push(String(e)));
  page.on("requestfailed", (r) => report.errors.push(`request failed: ${r.url()}`));
  if (rest.includes("--corrupt-avatar")) {
    await page.setRequestInterception(true);
    page.on("request", async (request) => {
      if (!request.url().includes("avatar.glb")) return request.continue();
      const response = await fetch(request.url());
      const bytes = Buffer.from(await response.arrayBuffer());
      request.respond({ status: 200, contentType: "model/gltf-binary", body: bytes.subarray(0, 4000) });
    });
  }
  const view = option("--view")?.split(",").map(Number);
  await page.setViewport({ width: view ? view[7] : 640, height: view ? view[8] : 480 });
  await page.goto(url, { waitUntil: "load", timeout: 120000 });
  await page.waitForFunction("window.f3g && (window.f3g.ready || window.f3g.error)",
    { timeout: 240000, polling: 500 });
  report.loadSeconds = (Date.now() - started) / 1000;
  report.ready = await page.evaluate("window.f3g.ready");
  report.pageError = await page.evaluate("window.f3g.error");
  report.errorShown = await page.$eval("#error", (e) => getComputedStyle(e).display !== "none" && e.textContent);
  if (report.pageError) throw new Error(`page: ${report.pageError}`);
  report.memoryBytes = (await page.metrics()).JSHeapUsedSize;
  if (view) {
    await page.evaluate((v) => window.f3g.setView(v.slice(0, 3), v.slice(3, 6), v[6], v[7], v[8]), view);
  }
  if (option("--frame") !== undefined) {
    await page.evaluate((f) => window.f3g.setFrame(f), Number(option("--frame")));
  }
  if (rest.includes("--slider")) {
    // Moving the slider to its end must change the frame the page shows.
    report.frameBefore = await page.evaluate("window.f3g.frame");
    await page.$eval("#frame", (s) => {
      s.value = s.max;
      s.dispatchEvent(new Event("input"));
    });
    report.frameAfter = await page.evaluate("window.f3g.frame");
  }
  // Let a few frames render (sorting settles), then take the picture.
  const rendered = await page.evaluate("window.f3g.rendered");
  await page.waitForFunction((r) => window.f3g.rendered > r + 5, { timeout: 120000 }, rendered);
  if (option("--measure") === undefined) {
    // Then until the picture stops changing: Spark sorts the splats in a worker, and on a loaded
    // machine the frames after a new view or pose can still draw them in the previous order.
    let previous = null;
    for (let i = 0; i < 80; i++) {
      const picture = Buffer.from(await page.screenshot());
      if (previous && picture.equals(previous)) break;
      previous = picture;
      await new Promise((r) => setTimeout(r, 250));
    }
  }
  if (option("--measure") !== undefined) {
    // Playing (the default) or, with --still, the frame rate of rendering alone.
    if (!rest.includes("--still")) await page.evaluate("document.getElementById('play').click()");
    await new Promise((r) => setTimeout(r, 1000 * Number(option("--measure"))));
    report.fps = await page.evaluate("window.f3g.fps");
  }
  await page.screenshot({ path: out });
} catch (e) {
  report.errors.push(`driver: ${e.message}`);
} finally {
  await browser.close();
  writeFileSync(reportPath, JSON.stringify(report, null, 1));
}

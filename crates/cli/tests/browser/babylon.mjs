// Loads a file with Babylon.js's own loaders (npm `babylonjs`, `babylonjs-loaders`: glTF for
// `.glb`, its splat loader for `.ply` and `.spz`) in headless Chromium, as a user of that viewer
// would, and writes a screenshot and a JSON report: the meshes the loader made, or its error.
// The page, the libraries and the file are served by request interception, so nothing listens
// on a port.
//
//   node babylon.mjs FILE.glb|.ply|.spz OUT.png REPORT.json
import { launchChromium } from "./chromium.mjs";
import { readFileSync, writeFileSync } from "fs";
import { createRequire } from "module";

const [avatar, out, reportPath] = process.argv.slice(2);
const name = "avatar." + avatar.split(".").pop();
const require = createRequire(import.meta.url);
const library = (name) => readFileSync(require.resolve(name));
const page = `<!doctype html><html><body style="margin:0">
<canvas id="c" style="width:480px;height:640px"></canvas>
<script src="/babylon.js"></script><script src="/babylonjs.loaders.min.js"></script>
<script>
window.result = { done: false };
const engine = new BABYLON.Engine(document.getElementById("c"), true, { preserveDrawingBuffer: true });
const scene = new BABYLON.Scene(engine);
scene.clearColor = new BABYLON.Color4(1, 1, 1, 1);
new BABYLON.ArcRotateCamera("camera", Math.PI / 2, Math.PI / 2, 3.4, new BABYLON.Vector3(0, 0.9, 0), scene);
BABYLON.SceneLoader.ImportMeshAsync("", "/", "${name}", scene).then((r) => {
  window.result.meshes = r.meshes.map((m) => m.getClassName());
  window.result.skeletons = r.skeletons.length;
  engine.runRenderLoop(() => scene.render());
  setTimeout(() => { window.result.done = true; }, 3000);
}).catch((e) => { window.result.error = String(e); window.result.done = true; });
</script></body></html>`;
const files = {
  "/index.html": ["text/html", Buffer.from(page)],
  "/babylon.js": ["text/javascript", library("babylonjs/babylon.js")],
  "/babylonjs.loaders.min.js": ["text/javascript", library("babylonjs-loaders/babylonjs.loaders.min.js")],
  ["/" + name]: ["application/octet-stream", readFileSync(avatar)],
};
const report = { errors: [], missing: [] };
const browser = await launchChromium();
try {
  const tab = await browser.newPage();
  tab.on("pageerror", (e) => report.errors.push(String(e)));
  await tab.setRequestInterception(true);
  tab.on("request", (request) => {
    const file = files[new URL(request.url()).pathname];
    if (file) request.respond({ status: 200, contentType: file[0], body: file[1] });
    else {
      // What the loader asked for that is not here (Babylon's SPZ reader fetches a decoder
      // from a CDN): listed, answered 404.
      report.missing.push(request.url());
      request.respond({ status: 404, body: "" });
    }
  });
  await tab.setViewport({ width: 480, height: 640 });
  await tab.goto("http://f3g.test/index.html");
  await tab.waitForFunction("window.result.done", { timeout: 240000, polling: 250 });
  Object.assign(report, await tab.evaluate("window.result"));
  await tab.screenshot({ path: out });
} catch (e) {
  report.errors.push(`driver: ${e.message}`);
} finally {
  await browser.close();
  writeFileSync(reportPath, JSON.stringify(report, null, 1));
}

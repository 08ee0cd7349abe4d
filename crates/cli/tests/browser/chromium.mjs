// Debian's headless Chromium as the browser tests start it: WebGL on SwiftShader, and none of
// the background connections this machine's closed network refuses.
import puppeteer from "puppeteer-core";

export function launchChromium() {
  return puppeteer.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    headless: true,
    args: [
      "--no-sandbox", "--disable-gpu-sandbox", "--use-angle=swiftshader", "--use-gl=angle",
      "--enable-unsafe-swiftshader", "--disable-dev-shm-usage", "--no-first-run",
      "--disable-background-networking", "--disable-component-update", "--disable-sync",
    ],
  });
}

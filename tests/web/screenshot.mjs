// The page as a user sees it, as a PNG: loads it in Debian's Chromium,
// waits until the variables show their values, then shoots the whole page.
// `chromium --headless --screenshot` alone shoots at the load event, before
// the page's data come, and with --virtual-time-budget it never ends: the
// live stream is a request that stays open.
//
//   node tests/web/screenshot.mjs http://127.0.0.1:5080/#Demo page.png [wait ms]
import { chromium } from "playwright-core";

const [url, file, wait = "3000"] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--headless", "--no-sandbox", "--disable-gpu"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 1000 } });
  await page.goto(url);
  // Rows with values, or a notice (the page needs the token).
  await page.waitForFunction(() =>
    document.querySelector("#vars td.value") || !document.getElementById("notice").hidden,
    null, { timeout: 15000 });
  await page.waitForTimeout(Number(wait));
  await page.screenshot({ path: file, fullPage: true });
} finally {
  await browser.close();
}

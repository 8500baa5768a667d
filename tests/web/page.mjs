// Drives the built-in web page in Debian's Chromium (playwright-core, no
// browser download) and prints what it saw as one JSON line; the checks are
// made by tests/web.rs.
//
//   node page.mjs <base url> <screenshot.png> [token]
//
// Steps: load the page; wait for the SINUS row and time how long its value
// takes to change; chart SINUS and wait for the chart to draw; switch to
// the range mode and read its status; with a token: log in and write
// SETPOINT from the page; screenshot the whole page.
import { chromium } from "playwright-core";

const [base, screenshot, token] = process.argv.slice(2);
// Console errors by step: only the refused write may log one (its 400).
let step = "load";
const result = { console_errors: [], page_errors: [] };
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
  ],
});
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 1000 } });
  page.on("console", (msg) => { if (msg.type() === "error") result.console_errors.push(`${step}: ${msg.text()}`); });
  page.on("pageerror", (err) => result.page_errors.push(String(err)));
  page.setDefaultTimeout(15000);

  await page.goto(base + "/#Demo");
  const value = page.locator('#vars tr[data-name="SINUS"] td.value');
  await page.waitForFunction(() => {
    const cell = document.querySelector('#vars tr[data-name="SINUS"] td.value');
    return cell && cell.textContent !== "—";
  });
  const first = await value.textContent();
  const started = Date.now();
  await page.waitForFunction(
    (old) => document.querySelector('#vars tr[data-name="SINUS"] td.value').textContent !== old,
    first,
    { timeout: 10000 },
  );
  result.value_changed_ms = Date.now() - started;
  result.quality = await page.locator('#vars tr[data-name="SINUS"] td.quality').textContent();
  result.link_state = await page.locator("#link-state").textContent();
  // The live stream polls every row it shows: each turns good, whether
  // its value changes or not.
  await page.waitForFunction(() => {
    const cells = [...document.querySelectorAll("#vars td.quality")];
    return cells.length > 0 && cells.every((c) => c.textContent === "good");
  }).catch(() => {});
  result.qualities = await page.evaluate(() => {
    const counts = {};
    for (const c of document.querySelectorAll("#vars td.quality")) counts[c.textContent] = (counts[c.textContent] || 0) + 1;
    return counts;
  });
  result.legend = (await page.locator("#legend").textContent()).replace(/\s+/g, " ").trim();
  result.ident = await page.locator("#ident").textContent();

  // Chart SINUS (and SETPOINT, so two series) and wait for points.
  await page.locator('#vars tr[data-name="SINUS"] td.chart input').check();
  await page.locator('#vars tr[data-name="SETPOINT"] td.chart input').check();
  await page.waitForFunction(() => window.plccoms.live.t.length >= 5, null, { timeout: 10000 });
  await page.waitForTimeout(300);
  result.chart_points = await page.evaluate(() => window.plccoms.live.t.length);
  result.chart_series = await page.evaluate(() => window.plccoms.plot.series.length - 1);
  // Pixels of the first series' colour (#2b6cb0) on the chart's canvas.
  result.chart_pixels = await page.evaluate(() => {
    const canvas = document.querySelector("#plot canvas");
    const ctx = canvas.getContext("2d");
    const { data } = ctx.getImageData(0, 0, canvas.width, canvas.height);
    let n = 0;
    for (let i = 0; i < data.length; i += 4) {
      if (Math.abs(data[i] - 43) < 30 && Math.abs(data[i + 1] - 108) < 30 && Math.abs(data[i + 2] - 176) < 30 && data[i + 3] > 100) n++;
    }
    return n;
  });

  if (token) {
    await page.locator("#token").fill(token);
    await Promise.all([page.waitForEvent("load"), page.locator("#login button").click()]);
    const row = page.locator('#vars tr[data-name="SETPOINT"]');
    await row.locator("input.write").waitFor();
    await page.waitForFunction(() => window.plccoms.charted.length > 0).catch(() => {});
    result.trend_after_login = await page.evaluate(() => window.plccoms.charted);
    result.boxes_after_login = await page.locator("#vars td.chart input:checked").count();
    await row.locator("input.write").fill("21.5");
    await row.locator("td.write button").click();
    await page.waitForFunction(() => {
      const r = document.querySelector('#vars tr[data-name="SETPOINT"] .write-result');
      return r && r.textContent !== "…" && r.textContent !== "";
    });
    result.write_result = await row.locator(".write-result").textContent();
    step = "refused write";
    await row.locator("input.write").fill("hot");
    await row.locator("td.write button").click();
    await page.waitForFunction(() => {
      const r = document.querySelector('#vars tr[data-name="SETPOINT"] .write-result');
      return r && r.classList.contains("err");
    });
    result.bad_write_result = await row.locator(".write-result").textContent();
    step = "after write";
    await page.locator('#vars tr[data-name="SINUS"] td.chart input').check();
    await page.waitForFunction(() => window.plccoms.live.t.length >= 5, null, { timeout: 10000 });
  } else {
    result.write_column_hidden = await page.locator('#vars tr[data-name="SETPOINT"] td.write').isHidden();
  }

  // Range mode without a historian says so; then back to live for the picture.
  await page.locator('input[name="mode"][value="range"]').check();
  await page.waitForFunction(() => !["", "loading…"].includes(document.getElementById("chart-status").textContent));
  result.range_status = await page.locator("#chart-status").textContent();
  await page.locator('input[name="mode"][value="live"]').check();
  await page.waitForTimeout(1500);
  await page.screenshot({ path: screenshot, fullPage: true });
} catch (err) {
  result.failure = String(err && err.stack || err);
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));

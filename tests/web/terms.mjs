// Drives the web page in Debian's Chromium for values in the user's terms
// and prints what it saw as one JSON line; tests/web.rs checks it.
//
//   node terms.mjs <base url> <token>
//
// Steps: the Demo section's time and REAL values as shown; tick SINUS
// (the historian records it) and count the points the trend starts with
// from before the tick; the Modbus section M: units, descriptions, Set
// boxes only where a write can succeed (after logging in), a refused
// write's reason.
import { chromium } from "playwright-core";

const [base, token] = process.argv.slice(2);
const result = { console_errors: [], page_errors: [] };
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
  ],
});
const text = (page, name, cell) => page.locator(`#vars tr[data-name="${name}"] td.${cell}`).textContent();
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 1000 } });
  page.on("console", (msg) => { if (msg.type() === "error") result.console_errors.push(msg.text()); });
  page.on("pageerror", (err) => result.page_errors.push(String(err)));
  page.setDefaultTimeout(15000);

  await page.goto(base + "/#Demo");
  await page.waitForFunction(() => {
    const cells = [...document.querySelectorAll("#vars td.quality")];
    return cells.length > 0 && cells.every((c) => c.textContent === "good");
  });
  result.demo = {};
  for (const name of ["DAT", "V_DT", "TIM", "V_TOD", "SETPOINT", "TEXT"]) result.demo[name] = await text(page, name, "value");

  // The historian records SINUS: ticked, its trend starts minutes back.
  const ticked = Date.now() / 1000;
  await page.locator('#vars tr[data-name="SINUS"] td.chart input').check();
  // Room for a loaded machine (the suite's other tests beside it: this
  // wait once passed 15 s there); if it never comes, what the page and
  // the history API held then says why.
  await page.waitForFunction((t) => {
    const live = window.plccoms.live;
    const series = live.ys.get("SINUS");
    return series && live.t.some((x, i) => x < t - 1 && series.data[i] != null);
  }, ticked, { timeout: 60000 }).catch(async (err) => {
    result.seed_state = await page.evaluate(async (t) => {
      const live = window.plccoms.live;
      const series = live.ys.get("SINUS");
      const answer = await fetch("/api/history?section=Demo&vars=SINUS&from=-1h&format=json");
      const rows = answer.ok ? await answer.json() : null;
      return {
        ticked: t,
        points: live.t.length,
        first: live.t[0] ?? null,
        series: series ? series.data.filter((y) => y != null).length : null,
        history_status: answer.status,
        history_rows: Array.isArray(rows) ? rows.length : null,
        history_first: Array.isArray(rows) && rows.length ? rows[0].time : null,
        seeds: window.plccoms.seeds || [],
      };
    }, ticked).catch((e) => String(e));
    throw err;
  });
  result.seeded_before_tick = await page.evaluate((t) => {
    const live = window.plccoms.live;
    const series = live.ys.get("SINUS");
    return live.t.filter((x, i) => x < t - 1 && series.data[i] != null).length;
  }, ticked);

  // The Modbus section, logged in.
  await page.locator('#tabs button[data-section="M"]').click();
  await page.waitForFunction(() => location.hash === "#M" && document.querySelector('#vars tr[data-name="LOCKED"]'));
  await page.locator("#token").fill(token);
  await Promise.all([page.waitForEvent("load"), page.locator("#login button").click()]);
  await page.locator('#vars tr[data-name="SETPOINT"] input.write').waitFor();
  await page.waitForFunction(() => document.querySelector('#vars tr[data-name="SETPOINT"] td.value').textContent !== "—");
  result.m = {
    setpoint_value: await text(page, "SETPOINT", "value"),
    setpoint_title: await page.locator('#vars tr[data-name="SETPOINT"] td.name').getAttribute("title"),
    setpoint_set_box: await page.locator('#vars tr[data-name="SETPOINT"] input.write').count(),
    locked_set_box: await page.locator('#vars tr[data-name="LOCKED"] input.write').count(),
    locked_write_cell: await text(page, "LOCKED", "write"),
    plc_run_set_box: await page.locator('#vars tr[data-name="__PLC_RUN"] input.write').count(),
  };
  const row = page.locator('#vars tr[data-name="WHEN"]');
  await row.locator("input.write").fill("2026-11-25T10:15:00.123Z");
  await row.locator("td.write button").click();
  await page.waitForFunction(() => {
    const r = document.querySelector('#vars tr[data-name="WHEN"] .write-result');
    return r && r.textContent !== "…" && r.textContent !== "";
  });
  result.m.when_write = await row.locator(".write-result").textContent();
  await page.waitForFunction(() => document.querySelector('#vars tr[data-name="WHEN"] td.value').textContent.startsWith("2026"));
  result.m.when_value = await text(page, "WHEN", "value");
} catch (err) {
  result.failure = String(err && err.stack || err);
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));

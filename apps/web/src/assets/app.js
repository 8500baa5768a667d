// The plccoms status page: sections, clients, a variable browser with live
// values (server-sent events from /api/sections/{s}/live), a trend chart
// (uPlot) live and from the historian, the log, and writes with the token.
// Plain browser JavaScript, no build step; everything it loads is served by
// the binary.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const NUMERIC = /^(BOOL|SINT|INT|DINT|LINT|USINT|UINT|UDINT|ULINT|BYTE|WORD|DWORD|LWORD|REAL|LREAL|TIME|TIME_OF_DAY|TOD)$/;
  const MAX_POINTS = 20000;
  const QUALITY = {
    good: "read by the last poll",
    not_polled: "nobody polls it (no client or page enabled it): the last value read, if any",
    stale: "polled, but the last poll did not read it",
    link_lost: "the link to the PLC is lost: the last value known",
  };
  // Sections per page of tabs, rows per page of variables: with 1,000
  // sections and 100,000 variables the page asks for and draws one page,
  // and the live stream polls only the rows on screen.
  const SECTION_PAGE = 20;
  const VAR_PAGE = 100;
  const COLORS = ["#2b6cb0", "#c53030", "#1f8a4c", "#b7791f", "#6b46c1", "#0987a0", "#d53f8c", "#4a5568"];

  const st = {
    session: null,
    sections: [],    // the page of sections the tabs show
    sectionPage: { filter: "", state: "", offset: 0, total: 0, all: 0 },
    section: null,
    varOffset: 0,
    shown: [],       // the names of the variable rows on screen
    vars: new Map(), // name -> {type, value, text, unit, description, writable, quality, changed, row}
    charted: [],     // names, in the order chosen
    source: null,
    live: { t: [], ys: new Map() },
    mode: "live",
    zoomed: false,
    plot: null,
    prevCycle: null,
    events: 0,
  };
  // For tests and the curious: window.plccoms.events counts live events.
  window.plccoms = st;

  async function api(path, options) {
    return (await apiResponse(path, options)).body;
  }

  // The body and the response (for X-Total-Count).
  async function apiResponse(path, options) {
    const response = await fetch(path, Object.assign({ credentials: "same-origin" }, options));
    let body = null;
    const type = response.headers.get("content-type") || "";
    if (type.includes("json")) body = await response.json();
    if (!response.ok) {
      const error = new Error((body && body.error) || response.status + " " + response.statusText);
      error.status = response.status;
      throw error;
    }
    return { body, response };
  }

  function notice(text) {
    $("notice").textContent = text || "";
    $("notice").hidden = !text;
  }

  const pad = (n) => String(n).padStart(2, "0");
  function clock(ms) {
    if (ms == null) return "";
    const d = new Date(ms);
    return `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}.${String(d.getMilliseconds()).padStart(3, "0")}`;
  }
  function dateTime(ms) {
    const d = new Date(ms);
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }
  function localInput(ms) {
    const d = new Date(ms);
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())}T${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }
  function ago(ms) {
    const s = Math.max(0, Math.round((Date.now() - ms) / 1000));
    if (s < 60) return `${s} s ago`;
    if (s < 3600) return `${Math.floor(s / 60)} min ago`;
    return `${Math.floor(s / 3600)} h ago`;
  }
  function bytes(n) {
    if (n < 1024) return `${n} B`;
    if (n < 1048576) return `${(n / 1024).toFixed(1)} KiB`;
    return `${(n / 1048576).toFixed(1)} MiB`;
  }
  function numeric(type, text) {
    if (text == null || !NUMERIC.test(type)) return null;
    const x = Number(text);
    return Number.isFinite(x) ? x : null;
  }
  const canWrite = () =>
    st.session && st.session.writes_possible && st.session.authenticated && st.section && !st.section.read_only;

  // A presented value (JSON: number, boolean, ISO 8601 text) as a number
  // for the live chart: TIME and TOD in seconds.
  function chartValue(type, value) {
    if (value == null || !NUMERIC.test(type)) return null;
    if (typeof value === "number") return value;
    if (typeof value === "boolean") return value ? 1 : 0;
    const text = String(value);
    let m = /^P(?:(\d+)D)?(?:T(?:(\d+)H)?(?:(\d+)M)?(?:(\d+(?:\.\d+)?)S)?)?$/.exec(text);
    if (m && text !== "P" && text !== "PT") {
      return Number(m[1] || 0) * 86400 + Number(m[2] || 0) * 3600 + Number(m[3] || 0) * 60 + Number(m[4] || 0);
    }
    m = /^(\d+):(\d\d):(\d\d(?:\.\d+)?)$/.exec(text);
    if (m) return Number(m[1]) * 3600 + Number(m[2]) * 60 + Number(m[3]);
    // The protocol's text (the history's older rows): TIME and TOD in ms.
    const x = Number(text);
    if (!Number.isFinite(x)) return null;
    return /^(TIME|TIME_OF_DAY|TOD)$/.test(type) ? x / 1000 : x;
  }

  // The ticked trend variables of each section survive a reload (logging
  // in reloads the page) for as long as the tab lives.
  const trendKey = (section) => `plccoms.trend.${section}`;
  function saveTrend() {
    if (!st.section) return;
    try {
      sessionStorage.setItem(trendKey(st.section.name), JSON.stringify(st.charted));
    } catch (e) {
      // Storage off: the trend is not kept.
    }
  }
  function savedTrend(section) {
    try {
      const names = JSON.parse(sessionStorage.getItem(trendKey(section)) || "[]");
      return Array.isArray(names) ? names.filter((n) => typeof n === "string") : [];
    } catch (e) {
      return [];
    }
  }

  // ---------------------------------------------------------------- session
  async function start() {
    st.session = await api("/api/session");
    $("version").textContent = st.session.version;
    $("login").hidden = !st.session.writes_possible || st.session.authenticated;
    $("whoami").hidden = !st.session.authenticated;
    if (st.session.reads_need_token && !st.session.authenticated) {
      notice("This page needs the HTTP_TOKEN: log in above.");
      return;
    }
    notice("");
    $("main").hidden = false;
    await refreshSections();
    const wanted = decodeURIComponent(location.hash.slice(1));
    const first = (wanted && (await sectionNamed(wanted))) || st.sections[0];
    if (first) selectSection(first.name, first);
    setInterval(refreshSection, 1000);
    setInterval(refreshSections, 5000);
    setInterval(refreshClients, 2000);
    setInterval(refreshLog, 5000);
    refreshLog();
  }

  $("login").addEventListener("submit", async (event) => {
    event.preventDefault();
    try {
      await api("/api/login", {
        method: "POST",
        headers: { "content-type": "application/json" },
        body: JSON.stringify({ token: $("token").value }),
      });
      location.reload();
    } catch (e) {
      notice(`Login failed: ${e.message}`);
    }
  });
  $("logout").addEventListener("click", async () => {
    await api("/api/logout", { method: "POST" });
    location.reload();
  });

  // ---------------------------------------------------------------- sections
  // The page of sections the tabs show (all of them in a small
  // configuration; a search box and paging from SECTION_PAGE on).
  async function refreshSections() {
    const p = st.sectionPage;
    const q = new URLSearchParams({ offset: String(p.offset), limit: String(SECTION_PAGE) });
    if (p.filter) q.set("filter", p.filter);
    if (p.state) q.set("state", p.state);
    let page;
    try {
      page = await apiResponse(`/api/sections?${q}`);
    } catch (e) {
      notice(`The server does not answer: ${e.message}`);
      return;
    }
    const narrowed = Boolean(p.filter || p.state);
    if (p.filter !== (q.get("filter") || "") || p.state !== (q.get("state") || "") || p.offset !== Number(q.get("offset"))) return; // asked again meanwhile
    notice("");
    p.total = Number(page.response.headers.get("x-total-count") || page.body.length);
    if (!narrowed) p.all = p.total;
    if (p.offset > 0 && p.offset >= p.total) {
      // A reload removed sections: back to the last page there is.
      p.offset = Math.max(0, Math.floor((p.total - 1) / SECTION_PAGE) * SECTION_PAGE);
      return refreshSections();
    }
    st.sections = page.body;
    const tabs = $("tabs");
    const names = st.sections.map((s) => s.name);
    if ([...tabs.children].map((b) => b.dataset.section).join("\n") !== names.join("\n")) {
      tabs.replaceChildren(
        ...st.sections.map((s) => {
          const b = document.createElement("button");
          b.type = "button";
          b.textContent = s.name;
          b.dataset.section = s.name;
          b.addEventListener("click", () => selectSection(s.name));
          return b;
        })
      );
    }
    for (const b of tabs.children) b.classList.toggle("active", st.section && b.dataset.section === st.section.name);
    $("section-pick").hidden = p.all <= SECTION_PAGE && !narrowed;
    $("section-count").textContent = p.total === 0
      ? "none match"
      : `${p.offset + 1}–${p.offset + st.sections.length} of ${p.total}${narrowed ? " matching" : " sections"}`;
    $("sections-prev").disabled = p.offset === 0;
    $("sections-next").disabled = p.offset + st.sections.length >= p.total;
  }

  let sectionFilterTimer = null;
  $("section-filter").addEventListener("input", () => {
    clearTimeout(sectionFilterTimer);
    sectionFilterTimer = setTimeout(() => {
      st.sectionPage.filter = $("section-filter").value.trim();
      st.sectionPage.offset = 0;
      refreshSections();
    }, 250);
  });
  $("section-state").addEventListener("change", () => {
    st.sectionPage.state = $("section-state").value;
    st.sectionPage.offset = 0;
    refreshSections();
  });
  $("sections-prev").addEventListener("click", () => {
    st.sectionPage.offset = Math.max(0, st.sectionPage.offset - SECTION_PAGE);
    refreshSections();
  });
  $("sections-next").addEventListener("click", () => {
    st.sectionPage.offset += SECTION_PAGE;
    refreshSections();
  });

  // One section, whether or not the tabs show it; null when there is none.
  async function sectionNamed(name) {
    const listed = st.sections.find((s) => s.name === name);
    if (listed) return listed;
    try {
      return await api(`/api/sections/${encodeURIComponent(name)}`);
    } catch (e) {
      return null;
    }
  }

  // The selected section's state, every second.
  async function refreshSection() {
    const s = st.section;
    if (!s) return;
    let now;
    try {
      now = await api(`/api/sections/${encodeURIComponent(s.name)}`);
    } catch (e) {
      if (e.status !== 404) notice(`The server does not answer: ${e.message}`);
      return;
    }
    notice("");
    if (st.section && st.section.name === now.name) {
      st.section = now;
      renderOverview(now);
    }
  }

  function renderOverview(s) {
    const badge = $("link-state");
    badge.textContent = s.link.state.replace("_", " ");
    badge.className = `badge ${s.link.state}`;
    $("link-since").textContent = `since ${dateTime(s.link.since_ms)}`;
    $("plc-addr").textContent = s.link.plc ? `PLC ${s.link.plc}` : "";
    $("ident").textContent = s.link.ident || "(not identified yet)";
    $("pubfiles").textContent = [s.pubfile_fixed, s.pubfile_user].filter(Boolean).join(", ") + ` · ${s.variables} variables`;
    const p = s.poll;
    let cycle = "…";
    if (st.prevCycle && st.prevCycle.section === s.name && p.cycles > st.prevCycle.cycles) {
      const ms = ((p.cycle_seconds_sum - st.prevCycle.sum) / (p.cycles - st.prevCycle.cycles)) * 1000;
      cycle = `${ms.toFixed(ms < 10 ? 2 : 1)} ms`;
    } else if (p.cycles > 0) {
      cycle = `${((p.cycle_seconds_sum / p.cycles) * 1000).toFixed(2)} ms`;
    }
    st.prevCycle = { section: s.name, cycles: p.cycles, sum: p.cycle_seconds_sum };
    $("cycle-time").textContent = cycle;
    $("period").textContent = `${p.period_ms} ms`;
    $("overruns").textContent = String(p.overruns);
    $("last-poll").textContent = p.last_poll_ms ? clock(p.last_poll_ms) : "never";
    $("client-count").textContent = String(s.clients);
    $("port").textContent = String(s.port);
    $("read-only").hidden = !s.read_only;
  }

  async function selectSection(name, known) {
    const s = known || (await sectionNamed(name));
    if (!s) return;
    st.section = s;
    st.prevCycle = null;
    history.replaceState(null, "", `#${encodeURIComponent(name)}`);
    for (const b of $("tabs").children) b.classList.toggle("active", b.dataset.section === name);
    renderOverview(s);
    st.charted = [];
    st.varOffset = 0;
    resetLive();
    await loadVars();
    await restoreTrend(savedTrend(name));
    refreshClients();
  }

  async function refreshClients() {
    if (!st.section) return;
    let list;
    try {
      list = await api(`/api/sections/${encodeURIComponent(st.section.name)}/clients`);
    } catch (e) {
      return;
    }
    $("clients").replaceChildren(
      ...list.map((c) => {
        const tr = document.createElement("tr");
        for (const text of [c.address, `${c.connected} (${ago(c.connected_ms)})`, String(c.enabled), bytes(c.queued_bytes)]) {
          const td = document.createElement("td");
          td.textContent = text;
          tr.append(td);
        }
        return tr;
      })
    );
    if (list.length === 0) {
      const tr = document.createElement("tr");
      const td = document.createElement("td");
      td.colSpan = 4;
      td.className = "dim";
      td.textContent = "no clients connected";
      tr.append(td);
      $("clients").append(tr);
    }
  }

  async function refreshLog() {
    let entries;
    try {
      entries = await api("/api/log");
    } catch (e) {
      return;
    }
    const items = entries.slice(-100).reverse().map((e) => {
      const li = document.createElement("li");
      li.className = e.level;
      li.textContent = `${dateTime(e.unix_ms)} ${e.level.padEnd(5)} ${e.message}`;
      return li;
    });
    if (items.length === 0) {
      const li = document.createElement("li");
      li.className = "dim";
      li.textContent = "none since start";
      items.push(li);
    }
    $("log").replaceChildren(...items);
  }

  // ---------------------------------------------------------------- variables
  let maskTimer = null;
  $("mask").addEventListener("input", () => {
    clearTimeout(maskTimer);
    maskTimer = setTimeout(() => {
      st.varOffset = 0;
      loadVars();
    }, 300);
  });
  $("vars-prev").addEventListener("click", () => {
    st.varOffset = Math.max(0, st.varOffset - VAR_PAGE);
    loadVars();
  });
  $("vars-next").addEventListener("click", () => {
    st.varOffset += VAR_PAGE;
    loadVars();
  });

  // The mask, offset and limit of the page of variables on screen.
  function varQuery() {
    const mask = $("mask").value.trim() || "*";
    return `vars=${encodeURIComponent(mask)}&offset=${st.varOffset}&limit=${VAR_PAGE}`;
  }

  async function loadVars() {
    const s = st.section;
    let list;
    try {
      list = await api(`/api/sections/${encodeURIComponent(s.name)}/values?${varQuery()}`);
    } catch (e) {
      $("var-count").textContent = e.message;
      return;
    }
    if (st.section !== s && st.section.name !== s.name) return;
    if (st.varOffset > 0 && list.values.length === 0 && list.total > 0) {
      // The table shrank under the page: its last page instead.
      st.varOffset = Math.floor((list.total - 1) / VAR_PAGE) * VAR_PAGE;
      return loadVars();
    }
    st.vars = new Map();
    const rows = list.values.map((v) => {
      const entry = {
        type: v.type, value: v.value, text: v.text, unit: v.unit, description: v.description,
        writable: v.writable, quality: v.quality, changed: v.changed_ms,
      };
      st.vars.set(v.name, entry);
      return makeRow(v.name, entry);
    });
    $("vars").replaceChildren(...rows);
    const paged = list.total > VAR_PAGE || list.offset > 0;
    $("var-count").textContent = paged && list.values.length
      ? `${list.offset + 1}–${list.offset + list.values.length} of ${list.total} variables`
      : `${list.total} variables`;
    $("var-pager").hidden = !paged;
    $("vars-prev").disabled = list.offset === 0;
    $("vars-next").disabled = list.next_offset == null;
    for (const th of document.querySelectorAll(".write-col")) th.hidden = !canWrite();
    st.shown = list.values.map((v) => v.name);
    openLive();
  }

  function makeRow(name, entry) {
    const tr = document.createElement("tr");
    tr.dataset.name = name;
    const cells = {};
    for (const key of ["chart", "name", "type", "value", "quality", "changed", "write"]) {
      cells[key] = document.createElement("td");
      cells[key].className = key;
      tr.append(cells[key]);
    }
    const box = document.createElement("input");
    box.type = "checkbox";
    box.setAttribute("aria-label", `chart ${name}`);
    box.disabled = !NUMERIC.test(entry.type);
    box.checked = st.charted.includes(name);
    box.addEventListener("change", () => toggleChart(name, box.checked));
    cells.chart.append(box);
    cells.name.textContent = name;
    if (entry.description) {
      cells.name.title = entry.description;
      const line = document.createElement("div");
      line.className = "description";
      line.textContent = entry.description;
      cells.name.append(line);
    }
    cells.type.textContent = entry.type;
    // A Set box only where a write can succeed.
    if (canWrite() && entry.writable) {
      const input = document.createElement("input");
      input.className = "write";
      input.setAttribute("aria-label", `new value of ${name}`);
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = "Set";
      const result = document.createElement("span");
      result.className = "write-result";
      const send = () => write(name, input.value, result);
      button.addEventListener("click", send);
      input.addEventListener("keydown", (e) => { if (e.key === "Enter") send(); });
      cells.write.append(input, button, result);
    } else if (!canWrite()) {
      cells.write.hidden = true;
    } else {
      cells.write.className = "write dim";
      cells.write.textContent = "read-only";
    }
    entry.cells = cells;
    entry.row = tr;
    paint(entry, false);
    return tr;
  }

  function paint(entry, flash) {
    const c = entry.cells;
    const shown = entry.text == null ? "—" : entry.text;
    c.value.textContent = shown;
    if (entry.unit && entry.text != null) {
      const unit = document.createElement("span");
      unit.className = "unit";
      unit.textContent = ` ${entry.unit}`;
      c.value.append(unit);
    }
    c.value.title = entry.text == null ? "" : `${shown}${entry.unit ? " " + entry.unit : ""}`;
    c.quality.textContent = entry.quality.replace("_", " ");
    c.quality.title = QUALITY[entry.quality] || "";
    c.quality.className = `quality q-${entry.quality}`;
    c.changed.textContent = entry.changed ? clock(entry.changed) : "";
    entry.row.className = `q-${entry.quality}`;
    if (flash) {
      entry.row.classList.add("flash");
      setTimeout(() => entry.row.classList.remove("flash"), 150);
    }
  }

  async function write(name, value, result) {
    result.className = "write-result";
    result.textContent = "…";
    try {
      const done = await api(`/api/sections/${encodeURIComponent(st.section.name)}/set`, {
        method: "POST",
        headers: { "content-type": "application/json" },
        body: JSON.stringify({ name, value }),
      });
      result.textContent = `✓ ${done.text}${done.unit ? " " + done.unit : ""}`;
    } catch (e) {
      result.className = "write-result err";
      result.textContent = e.message;
    }
  }

  // ---------------------------------------------------------------- live
  // Live values of the rows on screen and the charted variables only, by
  // name: the link polls these for the page, and nothing else.
  function openLive() {
    if (st.source) st.source.close();
    st.source = null;
    const names = [...new Set([...st.shown, ...st.charted])];
    if (names.length === 0) {
      $("live-status").textContent = "";
      return;
    }
    const masks = names.join(",");
    const url = `/api/sections/${encodeURIComponent(st.section.name)}/live?vars=${encodeURIComponent(masks)}`;
    const source = new EventSource(url);
    st.source = source;
    source.addEventListener("open", () => { $("live-status").textContent = "live"; });
    source.addEventListener("error", () => { $("live-status").textContent = "reconnecting…"; });
    source.addEventListener("values", (event) => onValues(JSON.parse(event.data)));
  }

  function onValues(batch) {
    st.events += 1;
    const t = batch.polled_ms || Date.now();
    for (const [name, value, quality, changed, text] of batch.values) {
      const entry = st.vars.get(name);
      if (entry) {
        const flash = entry.changed !== changed;
        entry.value = value;
        entry.text = text;
        entry.quality = quality;
        entry.changed = changed;
        paint(entry, flash);
      }
      const series = st.live.ys.get(name);
      if (series) series.last = chartValue(series.type, value);
    }
    if (!batch.online) {
      for (const entry of st.vars.values()) {
        if (entry.quality !== "link_lost") {
          entry.quality = "link_lost";
          paint(entry, false);
        }
      }
    }
    if (batch.table_changed || batch.link === "restored") resync();
    pushLive(t, batch.online);
  }

  async function resync() {
    try {
      const list = await api(`/api/sections/${encodeURIComponent(st.section.name)}/values?${varQuery()}`);
      for (const v of list.values) {
        const entry = st.vars.get(v.name);
        if (!entry) return loadVars();
        Object.assign(entry, { value: v.value, text: v.text, quality: v.quality, changed: v.changed_ms });
        paint(entry, false);
      }
    } catch (e) {
      // The next event tries again.
    }
  }

  // ---------------------------------------------------------------- chart
  function resetLive() {
    st.live = { t: [], ys: new Map() };
  }

  function addSeries(name, entry) {
    st.charted.push(name);
    st.live.ys.set(name, { type: entry.type, last: chartValue(entry.type, entry.value), data: st.live.t.map(() => null) });
  }

  function toggleChart(name, on) {
    const entry = st.vars.get(name);
    if (on && !st.charted.includes(name)) {
      addSeries(name, entry);
    } else if (!on) {
      st.charted = st.charted.filter((n) => n !== name);
      st.live.ys.delete(name);
    }
    saveTrend();
    buildPlot();
    openLive();
    if (st.mode === "range") loadRange();
    else if (on) seedTrend([name]);
  }

  // The trend ticked before a reload, ticked again (types from the API for
  // variables the mask does not show).
  async function restoreTrend(names) {
    if (names.length === 0) return;
    const s = st.section;
    const types = new Map();
    try {
      const list = await api(`/api/sections/${encodeURIComponent(s.name)}/vars?mask=${encodeURIComponent(names.join(","))}&limit=${names.length}`);
      for (const v of list.vars) types.set(v.name, v.type);
    } catch (e) {
      return;
    }
    if (st.section !== s) return;
    for (const name of names) {
      const entry = st.vars.get(name) || (types.has(name) ? { type: types.get(name), value: null } : null);
      if (!entry || !NUMERIC.test(entry.type) || st.charted.includes(name)) continue;
      addSeries(name, entry);
      const box = document.querySelector(`#vars tr[data-name="${CSS.escape(name)}"] td.chart input`);
      if (box) box.checked = true;
    }
    saveTrend();
    buildPlot();
    openLive();
    seedTrend(st.charted.slice());
  }

  // The live trend of variables the historian records starts with the
  // last minutes it recorded. Rows: {time: ISO, name, value: number} (or
  // the older {t: ms, name, value: text}).
  // A failed ask is tried again twice, a second apart (a busy server);
  // what each try found is kept in st.seeds (the last 10), for tests.
  async function seedTrend(names, tries = 3) {
    if (!st.session.historian || names.length === 0) return;
    const s = st.section;
    const to = Date.now();
    const from = to - Number($("window").value) * 1000;
    const q = new URLSearchParams({ section: s.name, vars: names.join(","), from: String(from), to: String(to), format: "json" });
    const seen = (what) => {
      st.seeds = (st.seeds || []).concat([`${new Date().toISOString()} ${names.join(",")}: ${what}`]).slice(-10);
    };
    let body;
    try {
      body = await api(`/api/history?${q}`);
    } catch (e) {
      // Not recorded, or the historian is busy: the trend starts live.
      seen(`failed: ${e.message}`);
      // Again only while the same section is shown.
      if (tries > 1 && e.status !== 503) setTimeout(() => st.section === s && seedTrend(names, tries - 1), 1000);
      return;
    }
    if (st.section !== s || !body) {
      seen(st.section !== s ? "another section now" : "no body");
      return;
    }
    const rows = Array.isArray(body) ? body : body.rows || body.samples || [];
    const points = new Map(); // name -> [[x, y], ..] ascending
    for (const r of rows) {
      const series = st.live.ys.get(r.name);
      if (!series || !names.includes(r.name)) continue;
      const ms = r.time != null ? Date.parse(r.time) : Number(r.t);
      if (!Number.isFinite(ms)) continue;
      const y = r.quality === "link_lost" ? null : chartValue(series.type, r.value);
      if (!points.has(r.name)) points.set(r.name, []);
      const list = points.get(r.name);
      if (list.length && ms / 1000 <= list[list.length - 1][0]) continue;
      list.push([ms / 1000, y]);
    }
    seen(`${rows.length} rows, ${points.size} series`);
    if (points.size === 0) return;
    mergeSeed(points);
    if (st.mode === "live") drawLive();
  }

  // History points before the live ones; a seeded series' gaps in the live
  // part filled with its recorded value then (the historian records
  // changes).
  function mergeSeed(points) {
    const live = st.live;
    const first = live.t.length ? live.t[0] : Infinity;
    const before = new Set();
    for (const list of points.values()) for (const [x] of list) if (x < first) before.add(x);
    const head = [...before].sort((a, b) => a - b);
    const times = head.concat(live.t);
    for (const [name, series] of live.ys) {
      const list = points.get(name);
      if (!list) {
        series.data = head.map(() => null).concat(series.data);
        continue;
      }
      let i = 0;
      let y = null;
      series.data = times.map((x, k) => {
        while (i < list.length && list[i][0] <= x) y = list[i++][1];
        const old = k >= head.length ? series.data[k - head.length] : null;
        return old != null ? old : y;
      });
    }
    live.t = times;
    if (live.t.length > MAX_POINTS) {
      live.t.splice(0, live.t.length - MAX_POINTS);
      for (const series of live.ys.values()) series.data.splice(0, series.data.length - MAX_POINTS);
    }
  }

  function pushLive(t, online) {
    if (st.charted.length === 0) return;
    const live = st.live;
    const x = t / 1000;
    if (live.t.length && x <= live.t[live.t.length - 1]) return;
    live.t.push(x);
    for (const series of live.ys.values()) series.data.push(online ? series.last : null);
    if (live.t.length > MAX_POINTS) {
      live.t.splice(0, live.t.length - MAX_POINTS);
      for (const series of live.ys.values()) series.data.splice(0, series.data.length - MAX_POINTS);
    }
    if (st.mode === "live") scheduleDraw();
  }

  let drawPending = false;
  function scheduleDraw() {
    if (drawPending) return;
    drawPending = true;
    requestAnimationFrame(() => {
      drawPending = false;
      drawLive();
    });
  }

  function drawLive() {
    if (!st.plot || st.mode !== "live") return;
    const data = [st.live.t, ...st.charted.map((n) => st.live.ys.get(n).data)];
    st.plot.setData(data, !st.zoomed);
    if (!st.zoomed && st.live.t.length) {
      // The window, or what there is of it when the chart is younger.
      const max = st.live.t[st.live.t.length - 1];
      const min = Math.min(max - 10, Math.max(st.live.t[0], max - Number($("window").value)));
      st.plot.setScale("x", { min, max });
    }
  }

  function plotSize() {
    return { width: Math.max(300, $("plot").clientWidth || 800), height: 320 };
  }

  function buildPlot(data) {
    if (st.plot) st.plot.destroy();
    st.plot = null;
    st.zoomed = false;
    $("plot").replaceChildren();
    if (st.charted.length === 0) {
      $("chart-status").textContent = "no variables chosen";
      return;
    }
    $("chart-status").textContent = "";
    const opts = Object.assign(plotSize(), {
      cursor: { drag: { x: true, y: false } },
      scales: { x: { time: true } },
      series: [{}, ...st.charted.map((name, i) => ({
        label: name,
        stroke: COLORS[i % COLORS.length],
        width: 1.5,
        spanGaps: false,
        points: { show: false },
      }))],
      axes: [{}, { size: 70 }],
      hooks: {
        setSelect: [(u) => { if (u.select.width > 0) st.zoomed = true; }],
      },
    });
    const initial = data || [st.live.t, ...st.charted.map((n) => st.live.ys.get(n).data)];
    st.plot = new uPlot(opts, initial, $("plot"));
    st.plot.over.addEventListener("dblclick", unzoom);
    if (!data) drawLive();
  }

  function unzoom() {
    st.zoomed = false;
    if (st.mode === "live") drawLive();
    else if (st.plot) st.plot.setData(st.plot.data, true);
  }
  $("unzoom").addEventListener("click", unzoom);
  $("window").addEventListener("change", () => drawLive());
  window.addEventListener("resize", () => { if (st.plot) st.plot.setSize(plotSize()); });

  for (const radio of document.querySelectorAll('input[name="mode"]')) {
    radio.addEventListener("change", () => {
      st.mode = radio.value;
      if (st.mode === "live") buildPlot();
      else loadRange();
    });
  }
  $("load").addEventListener("click", () => {
    document.querySelector('input[name="mode"][value="range"]').checked = true;
    st.mode = "range";
    loadRange();
  });
  const now = Date.now();
  $("from").value = localInput(now - 3600 * 1000);
  $("to").value = localInput(now);

  async function loadRange() {
    if (st.charted.length === 0) {
      buildPlot();
      return;
    }
    if (!st.session.historian) {
      buildPlot([[], ...st.charted.map(() => [])]);
      $("chart-status").textContent = "historian not enabled: no history is recorded by this server";
      return;
    }
    const from = new Date($("from").value).getTime();
    const to = new Date($("to").value).getTime();
    $("chart-status").textContent = "loading…";
    const q = new URLSearchParams({ section: st.section.name, vars: st.charted.join(","), from: String(from), to: String(to), format: "json" });
    let rows;
    try {
      // The rows of `plccoms history` (README, "Reading it back"): time
      // (ISO 8601 UTC), name, value (a number or null), text, quality.
      rows = await api(`/api/history?${q}`);
    } catch (e) {
      buildPlot([[], ...st.charted.map(() => [])]);
      $("chart-status").textContent = e.message;
      return;
    }
    // A row that is not good (a variable's, or a gap's: __LINK, __SERVER,
    // __DAMAGED, __ERROR for all) breaks the line until the next good value.
    const gap = (r) => r.name.startsWith("__");
    const tables = st.charted.map((name) => {
      const xs = [];
      const ys = [];
      for (const r of rows) {
        if (r.name !== name && !gap(r)) continue;
        let x = Date.parse(r.time) / 1000;
        const y = r.quality === "good" && typeof r.value === "number" ? r.value : null;
        if (xs.length && x <= xs[xs.length - 1]) {
          // One point per time: a break wins; a value right after a break
          // (a link's return is marked at its first values' time) goes
          // a microsecond after it.
          if (y === null) {
            ys[ys.length - 1] = null;
            continue;
          }
          if (ys[ys.length - 1] !== null) continue;
          x = xs[xs.length - 1] + 1e-6;
        }
        xs.push(x);
        ys.push(y);
      }
      return [xs, ys];
    });
    const data = uPlot.join(tables);
    buildPlot(data);
    const failed = rows.find((r) => r.name === "__ERROR");
    const samples = rows.filter((r) => !gap(r)).length;
    $("chart-status").textContent = `${samples} samples${failed ? ` · ${failed.text}` : ""}`;
  }

  start().catch((e) => notice(`The page could not start: ${e.message}`));
})();

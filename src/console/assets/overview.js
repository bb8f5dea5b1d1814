// Cell overview: one tile per machine and PLC, paged (96 a page) so a cell of 1024
// machines keeps at most a page of tiles in the DOM; live events update the models at once
// and the visible tiles in batches.
import {
  h, fill, api, enc, cellPath, cellNames, cellInfo, machinesOf, plcsOf, schedule, unschedule, setText,
  field, select, num, bytes, rate, linkWord, linkUp, inAlarm, isAlarm, protocolName, alarmText, enumWord, isProtocolA,
  dateTime, clock, nextId, takesG05,
} from './lib.js';

const PAGE = 96;
const MAX_LIVE = 4;
const POLL_MS = 15000;
const STATE_FILTERS = [
  ['', 'All'], ['up', 'Link up (idle, sending, receiving, alarm)'], ['notup', 'Link not up (down, connecting)'],
  ['LINK_STATE_DOWN', 'Down'], ['LINK_STATE_CONNECTING', 'Connecting'], ['LINK_STATE_IDLE', 'Idle'],
  ['LINK_STATE_SENDING', 'Sending'], ['LINK_STATE_RECEIVING', 'Receiving'], ['LINK_STATE_ALARM', 'Alarm'],
];
// Kept across visits so coming back from a machine shows the same page and filter.
const saved = { text: '', state: '', pages: {} };

export async function renderOverview(ctx, onlyCell) {
  ctx.title('Overview');
  const cells = onlyCell ? [onlyCell] : cellNames();
  const health = h('div', { id: 'health', class: 'health', 'aria-live': 'polite' });
  const text = h('input', { id: 'ov-filter', type: 'search', value: saved.text, placeholder: 'e.g. mill', autocomplete: 'off' });
  const stateSel = select('ov-state', STATE_FILTERS, saved.state);
  const controls = h('form', { class: 'controls', role: 'search', onsubmit: (e) => e.preventDefault() },
    field('Filter machines by name', text), field('Link state', stateSel));
  const sectionsBox = h('div', { class: 'cells' });
  ctx.main.append(h('h1', { tabindex: '-1' }, onlyCell ? `Cell ${onlyCell}` : 'Cell overview'), health, controls, sectionsBox);
  if (!cells.length) {
    sectionsBox.append(h('p', null, 'The console knows no cell yet.'));
    return;
  }

  const models = cells.map((cell) => newModel(cell));
  for (const m of models) sectionsBox.append(m.section);
  await Promise.all(models.map((m) => load(m).catch(() => { m.failed = true; })));
  if (!ctx.alive) return;

  const refilter = () => {
    saved.text = text.value.trim().toLowerCase();
    saved.state = stateSel.value;
    for (const m of models) {
      m.page = 0;
      renderTiles(m);
    }
  };
  let debounce = 0;
  text.addEventListener('input', () => {
    clearTimeout(debounce);
    debounce = setTimeout(refilter, 150);
  });
  stateSel.addEventListener('change', refilter);
  ctx.onCleanup(() => {
    clearTimeout(debounce);
    unschedule('ov:');
  });

  // Links and alarms are told apart: a machine in alarm still has its link up (the remote
  // buffer answers with its alarm), so "links up" never counts it out, and the alarms are
  // named on a line of their own.
  const renderHealth = () => {
    const rows = models.map(cellHealth);
    const total = rows.reduce((a, r) => a + r.n, 0);
    const up = rows.reduce((a, r) => a + r.up, 0);
    const alarms = rows.flatMap((r) => (models.length > 1 ? r.alarms.map((n) => `${n} (${r.cell})`) : r.alarms));
    const stDown = rows.reduce((a, r) => a + r.stationsDown, 0);
    const ok = up === total && !alarms.length && stDown === 0 && !models.some((m) => m.failed);
    health.className = `health ${ok ? 'ok' : 'bad'}`;
    const links = total === 1 ? `The machine link is ${up ? 'up' : 'down'}` : up === total ? `All ${total} machine links up` : `${up} of ${total} machine links up`;
    fill(health,
      h('p', { class: 'health-main', 'data-field': 'links' }, h('span', { class: 'icon', 'aria-hidden': 'true' }, up === total && !stDown ? '✔' : '⚠'),
        links + (stDown ? `, ${stDown} PLC station(s) down` : '')),
      alarms.length ? h('p', { class: 'health-main', 'data-field': 'alarms' }, h('span', { class: 'icon', 'aria-hidden': 'true' }, '⚠'),
        `${alarms.length} machine${alarms.length === 1 ? '' : 's'} in alarm: ${alarms.join(', ')}`) : null,
      models.length > 1 ? h('ul', null, rows.map((r) => h('li', null, r.text))) : null);
    // With one cell the banner says it all; the cell's own line would repeat it.
    for (const [i, m] of models.entries()) {
      setText(m.healthLine, rows[i].text);
      m.healthLine.hidden = models.length === 1;
    }
  };
  for (const m of models) {
    m.touch = (name) => {
      schedule('ov:health', renderHealth);
      const refs = m.visible.get(name);
      if (refs) schedule(`ov:tile:${m.cell}/${name}`, () => updateTile(refs, m.machines.get(name)));
    };
    m.touchPlc = (name) => {
      schedule('ov:health', renderHealth);
      const refs = m.plcTiles.get(name);
      if (refs) schedule(`ov:plc:${m.cell}/${name}`, () => updatePlcTile(refs, m.plcs.get(name)));
    };
    renderTiles(m);
  }
  // A browser keeps ~6 connections per server over HTTP/1.1 and each event stream holds
  // one: follow at most MAX_LIVE cells live, and re-read the others now and then.
  models.forEach((m, i) => {
    if (i < MAX_LIVE) {
      subscribe(ctx, m);
      return;
    }
    m.note.hidden = false;
    const timer = setInterval(async () => {
      await load(m).catch(() => {});
      if (!ctx.alive) return;
      renderTiles(m);
      renderHealth();
    }, POLL_MS);
    ctx.onCleanup(() => clearInterval(timer));
  });
  renderHealth();
}

function newModel(cell) {
  const info = cellInfo(cell) || {};
  const m = {
    cell, order: machinesOf(cell), plcOrder: plcsOf(cell), machines: new Map(), plcs: new Map(),
    page: saved.pages[cell] || 0, visible: new Map(), plcTiles: new Map(), touch() {}, touchPlc() {},
  };
  const headingId = `cell-${cell.replace(/[^A-Za-z0-9_-]/g, '_')}`;
  m.healthLine = h('p', { class: 'muted' });
  m.note = h('p', { class: 'small-text muted', hidden: true }, 'Re-read every 15 s here; ',
    h('a', { href: `#/cell/${enc(cell)}` }, `open cell ${cell} alone`), ' to follow it live.');
  m.plcBox = h('div', { class: 'tiles plc-tiles' });
  m.tilesBox = h('div', { class: 'tiles' });
  m.pagerTop = h('nav', { class: 'pager', 'aria-label': `Pages of cell ${cell}` });
  m.pagerBottom = h('nav', { class: 'pager', 'aria-label': `Pages of cell ${cell}, bottom` });
  m.section = h('section', { 'data-cell': cell, 'aria-labelledby': headingId, class: 'cell' },
    h('h2', { id: headingId }, `Cell ${cell}`, ' ',
      h('small', { class: 'muted' }, info.version ? `gateway ${info.version}` : '', info.started_unix_ms ? ` · up since ${dateTime(info.started_unix_ms)}` : '')),
    m.healthLine, m.note, m.plcBox, m.pagerTop, m.tilesBox, m.pagerBottom);
  m.tilesBox.addEventListener('click', (e) => {
    // The whole tile opens the machine; its own link and buttons keep their meaning.
    if (e.target.closest('a, button, input, select')) return;
    const a = e.target.closest('article')?.querySelector('h3 a');
    if (a) location.hash = a.getAttribute('href');
  });
  return m;
}

async function load(m) {
  const ov = await api('GET', `${cellPath(m.cell)}/overview`);
  m.failed = false;
  for (const st of ov.machines || []) {
    const old = m.machines.get(st.machine);
    const mm = old || { name: st.machine, job: null, alarm: null };
    mm.status = st;
    mm.alarm = st.last_alarm || mm.alarm;
    if (st.current_job_id && mm.job?.id !== st.current_job_id) mm.job = { id: st.current_job_id, phase: 'running', sent: 0, total: null, rate: 0 };
    m.machines.set(st.machine, mm);
    if (!m.order.includes(st.machine)) m.order.push(st.machine);
  }
  for (const p of ov.plcs || []) {
    m.plcs.set(p.plc, p);
    if (!m.plcOrder.includes(p.plc)) m.plcOrder.push(p.plc);
  }
}

function subscribe(ctx, m) {
  const live = ctx.live(m.cell, null, async () => {
    await load(m).catch(() => {});
    if (ctx.alive) renderTiles(m);
  });
  const machine = (name) => m.machines.get(name);
  live.on('status', (st) => {
    let mm = machine(st.machine);
    if (!mm) return;
    mm.status = st;
    if (st.last_alarm) mm.alarm = st.last_alarm;
    if (st.current_job_id && mm.job?.id !== st.current_job_id) mm.job = { id: st.current_job_id, phase: 'running', sent: 0, total: null, rate: 0 };
    m.touch(st.machine);
  });
  live.on('job', (ev) => {
    const mm = machine(ev.machine);
    if (!mm) return;
    applyJob(mm, ev);
    m.touch(ev.machine);
  });
  live.on('alarm', (a) => {
    const mm = machine(a.machine);
    if (!mm) return;
    mm.alarm = a;
    m.touch(a.machine);
  });
  live.on('di', (d) => {
    const mm = machine(d.machine);
    if (!mm || !mm.status) return;
    mm.status.di_image = d.value;
    m.touch(d.machine);
  });
  live.on('g05', (g) => {
    const mm = machine(g.machine);
    if (!mm || !mm.status) return;
    mm.status.g05 = g;
    m.touch(g.machine);
  });
  live.on('plc', (p) => {
    if (!m.plcs.has(p.plc)) return;
    m.plcs.set(p.plc, p);
    m.touchPlc(p.plc);
  });
  live.on('tag', (t) => {
    const p = m.plcs.get(t.plc);
    if (!p) return;
    const tags = p.tags || (p.tags = []);
    const i = tags.findIndex((x) => x.name === t.name);
    if (i >= 0) tags[i] = t;
    else tags.push(t);
    m.touchPlc(t.plc);
  });
  live.start();
}

// A machine's job as the tile shows it, from its events.
function applyJob(mm, ev) {
  let j = mm.job;
  if (!j || j.id !== ev.job_id) {
    if (ev.queued) return; // a queued job shows as the queue count until it starts
    j = mm.job = { id: ev.job_id, phase: 'running', sent: 0, total: null, rate: 0 };
  }
  if (ev.origin?.name) j.name = ev.origin.name;
  if (ev.started) {
    j.phase = 'running';
    if (ev.started.bytes_total != null) j.total = num(ev.started.bytes_total);
  } else if (ev.progress) {
    j.phase = 'running';
    j.sent = num(ev.progress.bytes_sent);
    if (ev.progress.bytes_total != null) j.total = num(ev.progress.bytes_total);
    j.rate = num(ev.progress.rate_bps);
  } else if (ev.completed) {
    j.phase = 'completed';
    j.sent = num(ev.completed.bytes_sent);
    j.total = j.total || j.sent;
    j.sent = j.total;
    j.rate = 0;
  } else if (ev.failed) {
    j.phase = 'failed';
    j.sent = num(ev.failed.byte_offset);
    j.reason = ev.failed.reason;
  } else if (ev.cancelled) {
    j.phase = 'cancelled';
    j.sent = num(ev.cancelled.byte_offset);
    j.reason = ev.cancelled.by ? `by ${ev.cancelled.by}` : '';
  }
}

function matches(mm) {
  if (saved.text && !mm.name.toLowerCase().includes(saved.text)) return false;
  const s = mm.status?.link_state;
  if (!saved.state) return true;
  if (saved.state === 'up') return linkUp(s);
  if (saved.state === 'notup') return !linkUp(s);
  return s === saved.state;
}

function renderTiles(m) {
  const names = m.order.filter((n) => m.machines.has(n) && matches(m.machines.get(n)));
  const pages = Math.max(1, Math.ceil(names.length / PAGE));
  m.page = Math.min(Math.max(0, m.page), pages - 1);
  saved.pages[m.cell] = m.page;
  const slice = names.slice(m.page * PAGE, (m.page + 1) * PAGE);
  m.visible = new Map();
  const frag = document.createDocumentFragment();
  for (const n of slice) {
    const refs = buildTile(m.cell, m.machines.get(n));
    m.visible.set(n, refs);
    frag.append(refs.el);
  }
  m.tilesBox.replaceChildren(frag);
  if (m.failed) m.tilesBox.append(h('p', { class: 'muted' }, 'This cell could not be read: see the message above.'));
  else if (!names.length) m.tilesBox.append(h('p', { class: 'muted' }, m.machines.size ? 'No machine matches the filter.' : 'This cell has no machines.'));
  renderPager(m, m.pagerTop, names.length, pages);
  // A second pager under the tiles only when there are pages to turn.
  m.pagerBottom.hidden = pages < 2;
  if (pages > 1) renderPager(m, m.pagerBottom, names.length, pages);

  m.plcTiles = new Map();
  m.plcBox.replaceChildren();
  for (const p of m.plcOrder) {
    if (!m.plcs.has(p)) continue;
    const refs = buildPlcTile(m.cell, p);
    updatePlcTile(refs, m.plcs.get(p));
    m.plcTiles.set(p, refs);
    m.plcBox.append(refs.el);
  }
}

function renderPager(m, pager, count, pages) {
  pager.replaceChildren();
  if (count <= PAGE) {
    if (count) pager.append(h('span', { class: 'muted' }, `${count} machine${count === 1 ? '' : 's'}`));
    return;
  }
  const go = (p) => {
    m.page = p;
    renderTiles(m);
  };
  const first = m.page * PAGE + 1;
  const last = Math.min(count, (m.page + 1) * PAGE);
  const sel = h('select', { id: nextId('page') });
  for (let i = 0; i < pages; i++) sel.append(h('option', { value: i, selected: i === m.page }, `Page ${i + 1} of ${pages}`));
  sel.addEventListener('change', () => go(Number(sel.value)));
  pager.append(
    h('button', { type: 'button', class: 'small', disabled: m.page === 0, onclick: () => go(m.page - 1) }, '‹ Previous'),
    h('label', { for: sel.id, class: 'sr-only' }, `Page of cell ${m.cell}`), sel,
    h('button', { type: 'button', class: 'small', disabled: m.page >= pages - 1, onclick: () => go(m.page + 1) }, 'Next ›'),
    h('span', { class: 'muted' }, `machines ${first}–${last} of ${count}`));
}

function cellHealth(m) {
  let n = 0;
  let up = 0;
  const by = {};
  const alarms = [];
  for (const name of m.order) {
    const mm = m.machines.get(name);
    if (!mm) continue;
    n++;
    const s = mm.status?.link_state || 'LINK_STATE_UNSPECIFIED';
    if (linkUp(s)) up++;
    else by[s] = (by[s] || 0) + 1;
    if (inAlarm(s)) alarms.push(name);
  }
  let stationsDown = 0;
  for (const p of m.plcs.values()) for (const s of p.stations || []) if (!s.up) stationsDown++;
  const parts = Object.entries(by).map(([s, c]) => `${c} ${linkWord(s).toLowerCase()}`);
  let text = m.failed ? `${m.cell}: not readable` : n === up ? `${m.cell}: all ${n} links up` : `${m.cell}: ${up} of ${n} links up (${parts.join(', ')})`;
  if (alarms.length) text += `; in alarm: ${alarms.join(', ')}`;
  if (stationsDown) text += `; ${stationsDown} PLC station(s) down`;
  return { cell: m.cell, n, up, alarms, stationsDown, text };
}

// ---- machine tile --------------------------------------------------------------------

function bitsBox(label) {
  const boxes = [];
  const wrap = h('span', { class: 'bits', role: 'img' });
  for (let b = 7; b >= 0; b--) {
    const i = h('i', null, '0');
    boxes.push(i);
    wrap.append(i);
  }
  const row = h('span', { class: 'io' }, h('span', { class: 'io-label' }, label), wrap, h('span', { class: 'muted io-na' }));
  return { row, wrap, boxes, na: row.lastChild, label };
}

function setBits(b, value, note) {
  const known = value != null;
  b.wrap.hidden = !known;
  setText(b.na, known ? '' : note);
  if (!known) return;
  const bin = (value & 255).toString(2).padStart(8, '0');
  b.wrap.setAttribute('aria-label', `${b.label} bits 7 to 0: ${bin}`);
  for (let k = 0; k < 8; k++) {
    const on = bin[k] === '1';
    setText(b.boxes[k], on ? '1' : '0');
    b.boxes[k].className = on ? 'on' : '';
  }
}

function buildTile(cell, mm) {
  const r = {};
  r.link = h('span', { class: 'badge', 'data-field': 'link' });
  r.protocol = h('span', { class: 'muted', 'data-field': 'protocol' });
  r.jobName = h('span', { 'data-field': 'job' });
  r.progress = h('progress', { 'data-field': 'progress', max: '1', 'aria-label': `Job progress on ${mm.name}` });
  r.rate = h('span', { class: 'muted small-text', 'data-field': 'rate' });
  r.jobBox = h('div', { class: 'job' }, r.jobName);
  r.jobTail = h('div', { class: 'job-tail' }, r.rate);
  r.queue = h('span', { class: 'muted', 'data-field': 'queue' });
  r.alarm = h('span', { 'data-field': 'alarm' });
  r.alarmLabel = h('span', { class: 'alarm-label' });
  r.alarmRow = h('div', { class: 'alarm-row', hidden: true }, r.alarmLabel, r.alarm);
  r.di = bitsBox('DI');
  r.do = bitsBox('DO');
  r.g05 = h('span', { 'data-field': 'g05' });
  r.g05Row = h('div', { class: 'g05-row', hidden: true }, h('span', { class: 'muted' }, 'G05: '), r.g05);
  r.wait = h('div', { class: 'muted small-text', 'data-field': 'waiting' });
  r.el = h('article', { 'data-tile': 'machine', 'data-cell': cell, 'data-name': mm.name, class: 'tile' },
    h('h3', null, h('a', { href: `#/cell/${enc(cell)}/machine/${enc(mm.name)}` }, mm.name)),
    h('div', { class: 'row' }, r.link, r.protocol, r.queue),
    r.jobBox, r.jobTail,
    r.alarmRow,
    r.ioRow = h('div', { class: 'row io-row' }, r.di.row, r.do.row),
    r.g05Row,
    r.wait);
  r.cell = cell;
  updateTile(r, mm);
  return r;
}

// What the tile says of alarms: the alarm while the machine is in it; a past alarm (one
// that no reset followed, such as a refused remote request) as past, with its time; after a
// reset, nothing.
function tileAlarm(st, a) {
  if (inAlarm(st.link_state)) {
    return { label: 'In alarm: ', text: isAlarm(a) ? alarmText(a) : 'the machine reports an alarm', active: true };
  }
  if (isAlarm(a)) return { label: `Last alarm ${clock(a.unix_ms)}: `, text: alarmText(a), active: false };
  return null;
}

function updateTile(r, mm) {
  const st = mm.status || {};
  const s = st.link_state || 'LINK_STATE_UNSPECIFIED';
  const word = linkWord(s);
  setText(r.link, word);
  r.link.dataset.state = s;
  r.link.className = `badge st-${word.toLowerCase()}`;
  r.el.dataset.state = word.toLowerCase();
  setText(r.protocol, protocolName(st.protocol));

  const j = mm.job;
  if (j) {
    const label = { running: 'Job', completed: 'Completed', failed: 'Failed', cancelled: 'Cancelled' }[j.phase];
    setText(r.jobName, `${label}: ${j.name || j.id}${j.reason ? ` (${j.reason})` : ''}`);
    r.jobBox.className = `job job-${j.phase}`;
    r.jobTail.hidden = false;
    if (!r.progress.isConnected) r.jobTail.prepend(r.progress);
    if (j.total) {
      r.progress.max = j.total;
      r.progress.value = Math.min(j.sent, j.total);
      const pct = Math.floor((100 * Math.min(j.sent, j.total)) / j.total);
      setText(r.rate, j.phase === 'running' ? `${pct}% · ${rate(j.rate)}` : `${pct}% · ${bytes(j.sent)}`);
    } else {
      if (j.phase === 'running') r.progress.removeAttribute('value'); // indeterminate until sizes arrive
      setText(r.rate, j.phase === 'running' ? `${bytes(j.sent)} · ${rate(j.rate)}` : bytes(j.sent));
    }
  } else {
    setText(r.jobName, 'No job');
    r.jobBox.className = 'job job-none';
    r.jobTail.hidden = true;
    if (r.progress.isConnected) r.progress.remove();
    setText(r.rate, '');
  }
  setText(r.queue, `queue ${num(st.jobs_waiting)}`);
  const a = mm.alarm;
  const shown = tileAlarm(st, a);
  r.alarmRow.hidden = !shown;
  setText(r.alarmLabel, shown?.label);
  setText(r.alarm, shown?.text);
  // The whole text wraps on the tile; the title holds it with its time as well.
  r.alarmRow.title = shown && isAlarm(a) ? `${alarmText(a)} (${dateTime(a.unix_ms)})` : '';
  r.alarmRow.classList.toggle('has-alarm', !!shown?.active);
  // DI and DO exist in the Protocol A family only (§4.4.1): elsewhere no row at all.
  r.ioRow.hidden = !isProtocolA(st.protocol);
  if (isProtocolA(st.protocol)) {
    setBits(r.di, st.di_image, 'not read');
    setBits(r.do, st.do_image, 'not set');
  }
  // G05 only where the machine takes G05 streams: elsewhere "none" would say nothing.
  const g = st.g05;
  r.g05Row.hidden = !takesG05(r.cell, mm.name, st);
  const g05 = g ? `${enumWord(g.state, 'G05_STATE_')} · buffer ${num(g.cnc_buffer)} · ${num(g.underruns)} underruns` : 'no stream yet';
  setText(r.g05, g05);
  r.g05.title = g05;
  setText(r.wait, st.storage_fault ? `Storage fault: ${st.storage_fault}` : st.waiting_for ? `Waiting for ${st.waiting_for}` : '');
}

// ---- PLC tile ------------------------------------------------------------------------

function buildPlcTile(cell, name) {
  const r = {};
  r.stations = h('p', { 'data-field': 'stations' });
  r.list = h('ul', { class: 'plain stations' });
  r.tags = h('dl', { class: 'tags' });
  r.el = h('article', { 'data-tile': 'plc', 'data-cell': cell, 'data-name': name, class: 'tile plc' },
    h('h3', null, h('a', { href: `#/cell/${enc(cell)}/plc/${enc(name)}` }, `PLC ${name}`)),
    r.stations, r.list, r.tags);
  r.el.addEventListener('click', (e) => {
    if (!e.target.closest('a, button')) location.hash = `#/cell/${enc(cell)}/plc/${enc(name)}`;
  });
  return r;
}

function updatePlcTile(r, p) {
  const st = p.stations || [];
  const up = st.filter((s) => s.up).length;
  setText(r.stations, `Stations: ${up} up, ${st.length - up} down`);
  r.el.dataset.state = up === st.length ? 'up' : 'down';
  r.list.replaceChildren(...st.map((s) => h('li', { class: s.up ? 'up' : 'down' },
    h('span', { class: `badge ${s.up ? 'st-idle' : 'st-down'}` }, s.up ? 'UP' : 'DOWN'), ` station ${s.station}`)));
  const tags = (p.tags || []).slice(0, 4);
  r.tags.replaceChildren(...tags.flatMap((t) => [
    h('dt', null, t.name),
    h('dd', { 'data-tag': t.name }, tagValue(t), t.quality && t.quality !== 'TAG_QUALITY_GOOD' ? h('span', { class: 'muted' }, ` (${enumWord(t.quality, 'TAG_QUALITY_')})`) : null),
  ]));
}

export function tagValue(t) {
  if (t.value == null) return '—';
  const v = Number(t.value);
  return Number.isInteger(v) ? String(v) : v.toFixed(Math.abs(v) < 10 ? 3 : 2);
}

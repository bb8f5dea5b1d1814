// One PLC link: stations, tags with live values and trends, tag writes, memory viewer.
import {
  h, api, can, enc, cellPath, query, schedule, unschedule, setText, field, table, scroller, act,
  notice, num, bytes, clock, enumWord, svg, polyPoints, extent, alertError,
} from './lib.js';
import { tagValue } from './overview.js';

const TREND_MS = 10 * 60 * 1000;
const MAX_POINTS = 600;

export async function renderPlc(ctx, cell, plc) {
  ctx.title(`PLC ${plc}`);
  const base = `${cellPath(cell)}/plcs/${enc(plc)}`;
  const main = ctx.main;
  main.append(h('p', { class: 'crumbs' }, h('a', { href: '#/' }, 'Overview'), ' › ', `cell ${cell}`),
    h('h1', { tabindex: '-1' }, `PLC ${plc}`));
  let st = await api('GET', base);
  if (!ctx.alive) return;

  const summary = h('div');
  const stationsBox = h('div');
  const tagsBody = h('tbody');
  const rows = new Map(); // tag name → refs
  const trends = new Map(); // tag name → [[ms, value], ...]

  const renderSummary = () => {
    const errs = Object.entries(st.receive_errors || {}).filter(([, n]) => num(n));
    const lineErrs = Object.entries(st.line_errors || {}).filter(([, n]) => num(n));
    summary.replaceChildren(h('dl', { class: 'kv' },
      h('dt', null, 'Mode'), h('dd', null, String(st.mode)),
      h('dt', null, 'Line'), h('dd', null, st.line || '—'),
      h('dt', null, 'Bytes in / out'), h('dd', null, `${bytes(st.bytes_in)} / ${bytes(st.bytes_out)}`),
      h('dt', null, 'Transfers received'), h('dd', null, String(num(st.transfers_received))),
      h('dt', null, 'Unexpected texts'), h('dd', null, String(num(st.unexpected_texts))),
      h('dt', null, 'Texts dropped'), h('dd', null, errs.length ? errs.map(([k, n]) => `${k}: ${num(n)}`).join(', ') : 'none'),
      h('dt', null, 'Line errors'), h('dd', { 'data-field': 'line-errors' }, lineErrs.length ? lineErrs.map(([k, n]) => `${k}: ${num(n)}`).join(', ') : 'none')));
    const t = table(['Station', 'State', 'Requests', 'Replies', 'Time-outs', 'Retries', 'BCC errors', 'Corrupted', 'Refused (down)', 'Error replies', 'Last error'], 'stations-table');
    t.setAttribute('aria-label', 'Stations');
    for (const s of st.stations || []) {
      const er = Object.entries(s.error_replies || {}).map(([k, n]) => `STA ${Number(k).toString(16).toUpperCase()}: ${num(n)}`).join(', ');
      t.tbody.append(h('tr', { 'data-station': String(s.station), class: s.up ? null : 'bad' },
        h('td', { class: 'num' }, String(s.station)),
        h('td', null, h('span', { class: `badge ${s.up ? 'st-idle' : 'st-down'}`, 'data-field': 'state' }, s.up ? 'UP' : 'DOWN')),
        ...[s.requests, s.replies, s.timeouts, s.retries, s.bcc_errors, s.corrupted_replies, s.refused_down].map((v) => h('td', { class: 'num' }, String(num(v)))),
        h('td', null, er || '—'), h('td', null, s.last_error || '—')));
    }
    stationsBox.replaceChildren((st.stations || []).length ? scroller(t) : h('p', { class: 'muted' }, 'No station.'));
  };

  const addPoint = (t) => {
    if (t.value == null) return;
    const ms = num(t.unix_ms) || Date.now();
    const pts = trends.get(t.name) || [];
    if (pts.length && pts[pts.length - 1][0] >= ms) return; // already have it (or older)
    pts.push([ms, Number(t.value)]);
    const cut = Date.now() - TREND_MS;
    while (pts.length > MAX_POINTS || (pts.length > 1 && pts[0][0] < cut && pts[1][0] < cut)) pts.shift();
    trends.set(t.name, pts);
  };

  const tagRow = (t) => {
    const r = {};
    r.value = h('td', { class: 'num', 'data-field': 'value' });
    r.quality = h('span', { 'data-field': 'quality' });
    r.time = h('td', { 'data-field': 'time' });
    r.line = svg('polyline', { fill: 'none', 'vector-effect': 'non-scaling-stroke' });
    r.svg = svg('svg', { class: 'trend', viewBox: '0 0 200 40', preserveAspectRatio: 'none', role: 'img', 'aria-label': `Trend of ${t.name}` }, r.line);
    r.range = h('span', { class: 'small-text muted' });
    let write = null;
    if (can('plc.tag') && t.writable) {
      const input = h('input', { type: 'number', step: 'any', id: `tag-write-${t.name.replace(/[^A-Za-z0-9_-]/g, '_')}`, class: 'narrow', inputmode: 'decimal' });
      const btn = h('button', { type: 'submit', class: 'small', 'data-action': 'write', 'data-tag': t.name }, 'Set');
      write = h('form', { class: 'inline' }, h('label', { for: input.id, class: 'sr-only' }, `New value for ${t.name}`), input, btn);
      write.addEventListener('submit', (e) => {
        e.preventDefault();
        if (input.value === '' || !Number.isFinite(Number(input.value))) {
          alertError(`Give a number for ${t.name}.`);
          return;
        }
        act(btn, async () => {
          const w = await api('POST', `${base}/tags/${enc(t.name)}`, { json: { value: Number(input.value) } });
          notice(`${w.plc}/${w.name} set to ${w.value}.`);
          input.value = '';
        });
      });
    }
    r.tr = h('tr', { 'data-tag': t.name },
      h('th', { scope: 'row' }, t.name), r.value, h('td', null, r.quality), r.time,
      h('td', { class: 'trend-cell' }, r.svg, r.range),
      can('plc.tag') ? h('td', null, write || h('span', { class: 'muted small-text' }, 'read-only')) : null);
    return r;
  };

  const updateTag = (t) => {
    let r = rows.get(t.name);
    if (!r) {
      r = tagRow(t);
      rows.set(t.name, r);
      tagsBody.append(r.tr);
    }
    setText(r.value, tagValue(t));
    const q = enumWord(t.quality, 'TAG_QUALITY_') || '—';
    setText(r.quality, q);
    r.quality.className = `badge ${t.quality === 'TAG_QUALITY_GOOD' ? 'st-idle' : t.quality === 'TAG_QUALITY_STATION_DOWN' ? 'st-down' : 'st-connecting'}`;
    setText(r.time, clock(t.unix_ms));
    drawTrend(t.name);
  };

  const drawTrend = (name) => {
    const r = rows.get(name);
    const pts = trends.get(name) || [];
    if (!r) return;
    const now = Date.now();
    // Tags publish on change: each value holds until the next (a step line), the last until now.
    const draw = [];
    for (const [t, v] of pts) {
      if (draw.length) draw.push([t, draw[draw.length - 1][1]]);
      draw.push([t, v]);
    }
    if (pts.length) draw.push([now, pts[pts.length - 1][1]]);
    const [lo, hi] = extent(draw.map((p) => p[1]));
    r.line.setAttribute('points', polyPoints(draw, 200, 40, now - TREND_MS, now, lo, hi));
    // Say what the line covers: a tag without `history = true` has only what came since the
    // page opened, and its line must not read as ten minutes of values.
    const from = pts.length ? pts[0][0] : now;
    const span = now - from >= TREND_MS - 5000 ? 'the last 10 min' : `since ${clock(from)}`;
    const label = pts.length ? `${fmt(lo)} … ${fmt(hi)}, ${span}` : 'no data yet';
    setText(r.range, label);
    r.range.setAttribute('data-field', 'trend-span');
    r.svg.setAttribute('aria-label', `Trend of ${name}, ${span}: ${pts.length} values, ${label}`);
  };

  const tagsTable = h('table', { class: 'tags-table', 'aria-label': 'Tags' },
    h('thead', null, h('tr', null, ['Tag', 'Value', 'Quality', 'Read at', 'Trend (up to 10 min)', can('plc.tag') ? 'Write' : null].filter(Boolean).map((x) => h('th', { scope: 'col' }, x)))), tagsBody);

  const sec = (title, id, ...kids) => h('section', { class: 'card', 'aria-labelledby': id }, h('h2', { id }, title), ...kids);
  main.append(sec('Link', 'sec-link', summary), sec('Stations', 'sec-stations', stationsBox),
    sec('Tags', 'sec-tags', (st.tags || []).length ? scroller(tagsTable) : h('p', { class: 'muted' }, 'This PLC has no tags.')));
  if (can('plc.mem')) main.append(sec('Memory', 'sec-mem', memViewer(base, st)));

  renderSummary();
  for (const t of st.tags || []) {
    addPoint(t);
    updateTag(t);
  }

  // Seed the trends from the history (tags with history = true have records).
  if (can('history.read') && (st.tags || []).length) {
    const tags = st.tags.map((t) => `${plc}/${t.name}`).join(',');
    api('GET', `${cellPath(cell)}/history${query({ tag: tags, _time: '[now(-10m)..]', limit: 10000 })}`, { quiet: true })
      .then((page) => {
        if (!ctx.alive) return;
        const old = new Map();
        for (const rec of page?.records || []) {
          const t = rec.tag;
          if (!t || t.plc !== plc || t.value == null) continue;
          if (!old.has(t.name)) old.set(t.name, []);
          old.get(t.name).push([num(t.unix_ms) || num(rec.unix_ms), Number(t.value)]);
        }
        for (const [name, pts] of old) {
          const merged = [...pts, ...(trends.get(name) || [])].sort((a, b) => a[0] - b[0]);
          trends.set(name, merged.slice(-MAX_POINTS));
          drawTrend(name);
        }
      })
      .catch(() => { /* trends start empty then: history may be off */ });
  }

  const live = ctx.live(cell, null, async () => {
    try {
      st = await api('GET', base, { quiet: true });
      if (!ctx.alive) return;
      renderSummary();
      for (const t of st.tags || []) {
        addPoint(t);
        updateTag(t);
      }
    } catch { /* next reconnect tries again */ }
  });
  live.on('plc', (p) => {
    if (p.plc !== plc) return;
    st = p;
    for (const t of p.tags || []) addPoint(t);
    schedule('plc:summary', renderSummary);
    for (const t of p.tags || []) schedule(`plc:tag:${t.name}`, () => updateTag(t));
  });
  live.on('tag', (t) => {
    if (t.plc !== plc) return;
    addPoint(t);
    const i = (st.tags || []).findIndex((x) => x.name === t.name);
    if (i >= 0) st.tags[i] = t;
    schedule(`plc:tag:${t.name}`, () => updateTag(t));
  });
  live.start();
  // Slide the trend window even when values hold still.
  const slide = setInterval(() => schedule('plc:slide', () => rows.forEach((_, n) => drawTrend(n))), 5000);
  ctx.onCleanup(() => {
    clearInterval(slide);
    unschedule('plc:');
  });
}

const fmt = (v) => (Number.isInteger(v) ? String(v) : v.toFixed(2));

function memViewer(base, st) {
  const stations = (st.stations || []).map((s) => s.station);
  const station = h('input', { id: 'mem-station', type: 'number', min: '0', step: '1', value: String(stations[0] ?? 0), class: 'narrow', inputmode: 'numeric' });
  const module = h('input', { id: 'mem-module', value: 'D', class: 'narrow', autocomplete: 'off', required: true });
  const address = h('input', { id: 'mem-address', type: 'number', min: '0', step: '1', value: '0', class: 'narrow', inputmode: 'numeric' });
  const count = h('input', { id: 'mem-count', type: 'number', min: '1', max: '110', step: '1', value: '16', class: 'narrow', inputmode: 'numeric' });
  const btn = h('button', { type: 'submit', id: 'mem-read' }, 'Read');
  const out = h('div', { id: 'mem-result', 'aria-live': 'polite' });
  const form = h('form', { class: 'stack' },
    h('div', { class: 'row' }, field('Station', station), field('Module', module, 'D, W9, W30:DI, …'), field('Address', address), field('Count', count)),
    h('div', { class: 'actions' }, btn), out);
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    act(btn, async () => {
      const w = await api('GET', `${base}/mem/${enc(station.value)}/${enc(module.value.trim())}/${enc(address.value)}${query({ count: count.value })}`);
      const wide = w.attribute !== 1;
      const t = table(['Address', 'Hex', 'Decimal', w.attribute === 1 ? 'Signed' : null].filter(Boolean), 'mem');
      t.setAttribute('aria-label', `Words of ${w.module} from ${w.address}`);
      (w.words || []).forEach((v, i) => {
        v = Number(v) >>> 0;
        t.tbody.append(h('tr', null, h('td', { class: 'num' }, String(w.address + i)),
          h('td', null, h('code', null, v.toString(16).toUpperCase().padStart(wide ? 8 : 4, '0'))),
          h('td', { class: 'num' }, String(v)),
          w.attribute === 1 ? h('td', { class: 'num' }, String(v > 32767 ? v - 65536 : v)) : null));
      });
      const attr = { 1: '16-bit', 2: 'BCD 32-bit', 3: 'SI file', 4: 'DI file' }[w.attribute] || `attribute ${w.attribute}`;
      out.replaceChildren(h('p', { class: 'small-text muted' }, `Station ${w.station}, module ${w.module} (${attr}), read at ${clock(w.unix_ms)}`), scroller(t));
    });
  });
  return form;
}

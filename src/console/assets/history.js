// The cell's history and audit trail: filters, a table of records newest (or oldest) first
// paged with `after`,
// CSV export of the same selection.
import {
  h, fill, api, can, alertError, enc, cellPath, query, field, select, act, bytes, dateTime, who, alarmText, enumWord,
  machinesOf, plcsOf, num,
} from './lib.js';

const KINDS = ['job', 'alarm', 'link', 'cnc', 'station', 'g05', 'tag', 'gateway', 'punch'];
const RANGES = [['1h', 'Last hour'], ['8h', 'Last 8 hours'], ['24h', 'Last 24 hours'], ['7d', 'Last 7 days'], ['custom', 'From … to …']];

export async function renderHistory(ctx, cell, params) {
  ctx.title('History');
  const main = ctx.main;
  const tabs = [];
  if (can('history.read')) tabs.push(['history', 'History']);
  if (can('audit.read')) tabs.push(['audit', 'Audit trail']);
  main.append(h('p', { class: 'crumbs' }, h('a', { href: '#/' }, 'Overview'), ' › ', `cell ${cell}`),
    h('h1', { tabindex: '-1' }, 'History and audit'));
  if (!tabs.length) {
    main.append(h('p', null, 'Your roles may read neither the history nor the audit trail.'));
    return;
  }
  let tab = tabs.some(([k]) => k === params.get('tab')) ? params.get('tab') : tabs[0][0];

  // Filters
  const names = [...machinesOf(cell), ...plcsOf(cell)];
  const machine = select('hist-machine', [['', 'All'], ...names.map((n) => [n, n])], params.get('machine') || '');
  const kind = select('hist-kind', [['', 'All but tag values'], ...KINDS.map((k) => [k, k])], params.get('kind') || '');
  const range = select('hist-range', RANGES, params.get('range') || '24h');
  const from = h('input', { id: 'hist-from', type: 'datetime-local', value: params.get('from') || '', step: '1' });
  const to = h('input', { id: 'hist-to', type: 'datetime-local', value: params.get('to') || '', step: '1' });
  const limit = select('hist-limit', [['100', '100'], ['200', '200'], ['500', '500'], ['1000', '1000']], params.get('limit') || '100');
  // What just happened on top by default; oldest first reads a shift as it went.
  const order = select('hist-order', [['newest', 'Newest first'], ['oldest', 'Oldest first']], params.get('order') || 'newest');
  const kindField = field('Kind', kind);
  const custom = h('div', { class: 'row' }, field('From (local time)', from), field('To (local time)', to, 'empty: now'));
  const showBtn = h('button', { type: 'submit', id: 'hist-show' }, 'Show');
  const form = h('form', { class: 'card stack', role: 'search', 'aria-label': 'Filters' },
    h('div', { class: 'row' }, field('Machine or PLC', machine), kindField, field('Time', range), field('Order', order), field('Per page', limit)),
    custom, h('div', { class: 'actions' }, showBtn));

  const tabBar = h('div', { role: 'tablist', class: 'tabs', 'aria-label': 'Records' });
  const tabButtons = tabs.map(([k, label]) => h('button', { type: 'button', role: 'tab', id: `tab-${k}`, 'aria-controls': 'hist-panel' }, label));
  tabBar.append(...tabButtons);
  const status = h('p', { class: 'muted', 'aria-live': 'polite' });
  const csv = h('a', { class: 'button', id: 'hist-csv', download: '' }, 'Export CSV');
  const pager = h('div', { class: 'pager' });
  const tableBox = h('div');
  const panel = h('div', { id: 'hist-panel', role: 'tabpanel' }, h('div', { class: 'row' }, status, csv), tableBox, pager);
  main.append(tabs.length > 1 ? tabBar : null, form, h('section', { class: 'card', 'aria-label': 'Records' }, panel));

  const syncUi = () => {
    custom.hidden = range.value !== 'custom';
    kindField.hidden = tab === 'audit';
    tabButtons.forEach((b, i) => {
      const on = tabs[i][0] === tab;
      b.setAttribute('aria-selected', on ? 'true' : 'false');
      b.tabIndex = on ? 0 : -1;
    });
    panel.setAttribute('aria-labelledby', `tab-${tab}`);
  };
  range.addEventListener('change', syncUi);

  let afters = []; // the `after` of each earlier page, for going back
  let after = '';

  const selection = () => {
    const p = { _time: timeParam(range.value, from.value, to.value), machine: machine.value };
    if (tab === 'history') p.kind = kind.value;
    p.limit = limit.value;
    p.order = order.value;
    return p;
  };

  const load = async () => {
    const sel = selection();
    if (sel._time === null) {
      alertError('Give a “from” time for the range, or choose one of the last hours or days.');
      from.focus();
      return;
    }
    // Keep the filters in the address so the view can be bookmarked (without re-rendering).
    const hp = new URLSearchParams({ tab, machine: machine.value, kind: kind.value, range: range.value, from: from.value, to: to.value, order: order.value, limit: limit.value });
    for (const [k, v] of Array.from(hp.entries())) if (!v) hp.delete(k);
    history.replaceState(null, '', `#/cell/${enc(cell)}/history?${hp}`);
    const url = `${cellPath(cell)}/${tab}${query({ ...sel, after })}`;
    csv.href = `/api/v1${url}&format=csv`; // the page shown, as CSV
    status.textContent = 'Loading…';
    const page = await api('GET', url);
    if (!ctx.alive) return;
    const recs = page.records || [];
    status.textContent = `${recs.length} record${recs.length === 1 ? '' : 's'} from ${dateTime(page.from_unix_ms)} to ${dateTime(page.to_unix_ms)}, ${order.value === 'newest' ? 'newest' : 'oldest'} first${afters.length ? `, page ${afters.length + 1}` : ''}${page.more ? '; more follow' : ''}.`;
    const t = h('table', { id: 'history-table', 'aria-label': tab === 'audit' ? 'Audit records' : 'History records' },
      h('thead', null, h('tr', null, ['Time', '#', tab === 'audit' ? 'Target' : 'Machine', 'Kind', 'What'].map((x) => h('th', { scope: 'col' }, x)))));
    const body = h('tbody');
    for (const r of recs) {
      const [k, text, bad] = describe(r);
      body.append(h('tr', { 'data-seq': String(r.seq), class: bad ? 'bad' : null },
        h('td', { class: 'nowrap' }, dateTime(r.unix_ms)), h('td', { class: 'num' }, String(r.seq)),
        h('td', null, r.machine || (r.audit?.target) || '—'), h('td', null, k), h('td', null, text)));
    }
    t.append(body);
    tableBox.replaceChildren(recs.length ? h('div', { class: 'scroll', tabindex: '0', role: 'region', 'aria-label': 'Records table' }, t)
      : h('p', { class: 'muted' }, 'No record matches.'));
    fill(pager,
      afters.length ? h('button', { type: 'button', class: 'small', onclick: (e) => act(e.currentTarget, () => { after = afters.pop(); return load(); }) }, '‹ Previous page') : null,
      page.more ? h('button', { type: 'button', class: 'small', onclick: (e) => act(e.currentTarget, () => { afters.push(after); after = String(page.next_after); return load(); }) }, 'Next page ›') : null);
  };

  const restart = () => {
    afters = [];
    after = '';
    return load().catch(() => { status.textContent = 'The records could not be read: see the message above.'; });
  };
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    act(showBtn, restart);
  });
  tabButtons.forEach((b, i) => {
    b.addEventListener('click', () => {
      tab = tabs[i][0];
      syncUi();
      restart();
    });
    b.addEventListener('keydown', (e) => {
      if (e.key !== 'ArrowRight' && e.key !== 'ArrowLeft') return;
      const j = (i + (e.key === 'ArrowRight' ? 1 : tabs.length - 1)) % tabs.length;
      tabButtons[j].focus();
      tabButtons[j].click();
    });
  });
  syncUi();
  await restart();
}

// zenoh's `_time` range: a preset as now(-…), or the datetime-local inputs in UTC.
function timeParam(range, from, to) {
  if (range !== 'custom') return `[now(-${range})..]`;
  if (!from) return null;
  const iso = (v) => new Date(v).toISOString().replace(/\.\d{3}Z$/, 'Z');
  return `[${iso(from)}..${to ? iso(to) : ''}]`;
}

function jobText(j) {
  const o = j.origin || {};
  const p = o.program || {};
  const src = p.library ? `${p.library} revision ${p.revision}` : `${o.name || 'inline'} (sha256 ${(p.sha256 || '').slice(0, 12)})`;
  const outcome = {
    JOB_OUTCOME_COMPLETED: 'completed',
    JOB_OUTCOME_FAILED: `failed: ${j.alarm_number ? j.alarm_number + ' ' : ''}${j.reason}`,
    JOB_OUTCOME_CANCELLED: j.reason || 'cancelled',
  }[j.outcome] || 'ended';
  return `Job ${j.job_id} ${src}, ${bytes(j.bytes_sent)} of ${bytes(j.bytes_total)} sent, by ${who(o.submitted_by)}: ${outcome}`;
}

// [kind, one line, is it bad news]
export function describe(r) {
  if (r.job) return ['job', jobText(r.job), r.job.outcome === 'JOB_OUTCOME_FAILED'];
  if (r.alarm) return ['alarm', alarmText(r.alarm), r.alarm.kind !== 'ALARM_KIND_CNC_RESET'];
  if (r.link != null) return ['link', `Link ${enumWord(r.link, 'LINK_STATE_')}`, r.link === 'LINK_STATE_DOWN' || r.link === 'LINK_STATE_ALARM'];
  if (r.cnc != null) return ['cnc', `CNC ${enumWord(r.cnc, 'MACHINE_ACTIVITY_')}`, r.cnc === 'MACHINE_ACTIVITY_ALARM'];
  if (r.station) return ['station', `Station ${r.station.station} ${r.station.up ? 'up' : 'down'}${r.station.reason ? `: ${r.station.reason}` : ''}`, !r.station.up];
  if (r.g05) {
    const g = r.g05;
    return ['g05', `G05 stream ${g.stream_id} ${enumWord(g.state, 'G05_STATE_')} (${enumWord(g.end_reason, 'G05_END_REASON_')}): ${num(g.received)} blocks, ${num(g.underruns)} underruns (estimated)${g.last_error ? `; ${g.last_error}` : ''}`, g.state === 'G05_STATE_FAILED'];
  }
  if (r.tag) return ['tag', `${r.tag.plc}/${r.tag.name} = ${r.tag.value == null ? '—' : r.tag.value} (${enumWord(r.tag.quality, 'TAG_QUALITY_')})`, false];
  if (r.punch) {
    const p = r.punch;
    const c = p.comparison;
    let against = 'not compared';
    if (p.damaged) against = `damaged: ${p.damage}`;
    else if (p.request) against = `remote request for ${p.request.program}`;
    else if (c) against = c.same ? `same as ${c.library_name} rev ${c.revision}` : `${c.blocks_changed} changed, ${c.blocks_added} added, ${c.blocks_removed} removed against ${c.library_name} rev ${c.revision}`;
    return ['punch', `Punched ${p.name}${p.library_name ? `, stored as ${p.library_name}` : ', not stored'}: ${against}`, !!p.damaged];
  }
  if (r.gateway) return ['gateway', `Gateway ${enumWord(r.gateway.event, 'EVENT_')} (${r.gateway.version})`, r.gateway.event === 'EVENT_STOPPED'];
  if (r.audit) {
    const a = r.audit;
    let by = who(a.origin);
    if (a.principal) by += ` [${a.principal}]`;
    else if (a.roles?.length) by += ` [role ${a.roles.join('|')}]`;
    const outcome = a.ok ? 'ok' : `refused (${String(a.code).replace(/^ERROR_CODE_/, '')}): ${a.error}`;
    return [a.action, `${a.detail || a.target} by ${by}: ${outcome}`, !a.ok];
  }
  return [enumWord(r.kind, 'HISTORY_KIND_') || '?', '', false];
}

// One machine: link and SAT, queue, recent jobs, sending a program, DO, alarms, punched
// programs, a live G05 chart and utilisation by hour.
import {
  h, fill, api, can, enc, cellPath, query, schedule, unschedule, setText, field, select, table, scroller,
  act, notice, num, bytes, rate, dateTime, clock, duration, linkWord, protocolName, isProtocolA,
  alarmText, enumWord, jobKind, who, b64text, revState, svg, polyPoints, extent, inAlarm, isAlarm, takesG05,
} from './lib.js';

export async function renderMachine(ctx, cell, name) {
  ctx.title(name);
  const base = `${cellPath(cell)}/machines/${enc(name)}`;
  const main = ctx.main;
  const header = h('div', { class: 'page-head' });
  main.append(h('p', { class: 'crumbs' }, h('a', { href: '#/' }, 'Overview'), ' › ', `cell ${cell}`),
    h('h1', { tabindex: '-1' }, `Machine ${name}`), header);

  let snap = await api('GET', base);
  if (!ctx.alive) return;
  const jobs = new Map(); // job_id → latest JobEvent
  const origins = new Map(); // job_id → JobOrigin (progress events carry none)
  // Jobs whose end (completed, failed, cancelled) was seen: the end is final, so a queue
  // read a moment before it, or a progress event coalesced behind it, never shows them as
  // running again.
  const ended = new Set();
  const isEnd = (ev) => !!(ev.completed || ev.failed || ev.cancelled);
  const takeJob = (ev) => {
    if (ev.origin) origins.set(ev.job_id, ev.origin);
    if (isEnd(ev)) ended.add(ev.job_id);
    else if (ended.has(ev.job_id)) return;
    const old = jobs.get(ev.job_id);
    if (!old || isEnd(ev) || (!isEnd(old) && num(old.unix_ms) <= num(ev.unix_ms))) jobs.set(ev.job_id, ev);
  };
  const takeJobs = (list) => {
    for (const ev of list || []) takeJob(ev);
  };
  const dropEnded = (q) => {
    if (!q) return;
    if (q.active && ended.has(q.active.job_id)) q.active = null;
    if (q.waiting) q.waiting = q.waiting.filter((j) => !ended.has(j.job_id));
  };
  takeJobs(snap.jobs);
  dropEnded(snap.queue);

  // Two columns on wide screens: jobs on the left, the link and its signals on the right.
  const colA = h('div', { class: 'col' });
  const colB = h('div', { class: 'col' });
  main.append(h('div', { class: 'grid' }, colA, colB));
  const sec = (title, id, ...kids) => h('section', { class: 'card', 'aria-labelledby': id }, h('h2', { id }, title), ...kids);

  // ---- status: link, SAT, counters
  const statusBox = h('div');
  colB.append(sec('Link and remote buffer', 'sec-status', statusBox));
  const renderStatus = () => {
    const st = snap.status || {};
    const word = linkWord(st.link_state);
    fill(header, [h('div', { class: 'row' },
      h('span', { class: `badge st-${word.toLowerCase()}`, 'data-field': 'link', 'data-state': st.link_state }, word),
      h('span', null, protocolName(st.protocol)),
      st.waiting_for ? h('span', { class: 'muted' }, `waiting for ${st.waiting_for} since ${clock(st.waiting_since_unix_ms)}`) : null,
      snap.queue?.active ? h('span', { 'data-field': 'active-job' }, `job ${snap.queue.active.job_id} active`) : null,
      h('span', { class: 'muted' }, `as of ${clock(st.unix_ms)}`)),
    // The alarm the machine is in, whole; none after a reset.
    inAlarm(st.link_state) ? h('p', { class: 'warn-text', 'data-field': 'alarm' }, 'In alarm: ',
      isAlarm(st.last_alarm) ? `${alarmText(st.last_alarm)} (since ${clock(st.last_alarm.unix_ms)})` : 'the machine reports an alarm') : null,
    st.storage_fault ? h('p', { class: 'warn-text' }, `Storage fault: ${st.storage_fault} — submits are refused meanwhile.`) : null]);
    fill(statusBox, satView(st), countersView(st.counters || {}), ioView(st));
  };

  // ---- queue and recent jobs
  const queueBox = h('div');
  const recentBox = h('div');
  colA.append(sec('Queue', 'sec-queue', queueBox));
  let activeRefs = null;
  const renderQueue = () => {
    const q = snap.queue || {};
    const t = table(['Job', 'Name', 'Program', 'Priority', 'Progress', 'Accepted', ''], 'jobs');
    t.setAttribute('aria-label', 'Job queue');
    activeRefs = null;
    const row = (j, active) => {
      const o = origins.get(j.job_id);
      const cancel = can('job.cancel') ? h('button', { type: 'button', class: 'small', 'data-action': 'cancel', 'data-job': j.job_id,
        onclick: (e) => act(e.currentTarget, async () => {
          await api('POST', `${base}/jobs/${enc(j.job_id)}/cancel`);
          notice(`Cancel of job ${j.job_id} requested.`);
          refetch();
        }) }, 'Cancel') : null;
      let total = num(j.bytes_total);
      let sent = num(j.bytes_sent);
      let prog = h('span', { class: 'muted' }, 'waiting');
      const tr = h('tr', { 'data-job': j.job_id, class: active ? 'active' : null });
      if (active) {
        // The latest progress event may be newer than the queue read.
        const last = jobs.get(j.job_id);
        if (last?.progress) {
          sent = Math.max(sent, num(last.progress.bytes_sent));
          total = num(last.progress.bytes_total) || total;
        }
        const p = h('progress', { 'data-field': 'progress', max: String(total || 1), value: String(Math.min(sent, total || 1)), 'aria-label': `Progress of job ${j.job_id}` });
        const txt = h('span', { class: 'small-text' });
        // The last block the remote buffer took whole: the CNC is at most there.
        const fed = h('div', { class: 'small-text muted code', 'data-field': 'block-fed', title: 'The last block the remote buffer took whole: the CNC executes up to it' });
        prog = h('span', { class: 'prog' }, p, txt, fed);
        activeRefs = { id: j.job_id, p, txt, total, fed };
        setText(txt, progressText(sent, total, 0));
        if (last?.progress?.block) setText(fed, `fed: ${last.progress.block}`);
      }
      tr.append(h('td', { class: 'nowrap' }, j.job_id, ' ', active ? h('span', { class: 'badge st-sending' }, 'ACTIVE') : null), h('td', null, j.name),
        h('td', null, programRef(o?.program)), h('td', { class: 'num' }, j.priority),
        h('td', null, prog), h('td', null, clock(j.accepted_unix_ms)), h('td', null, cancel));
      return tr;
    };
    if (q.active) t.tbody.append(row(q.active, true));
    for (const j of q.waiting || []) t.tbody.append(row(j, false));
    queueBox.replaceChildren(q.active || q.waiting?.length ? scroller(t) : h('p', { class: 'muted' }, 'No job is queued.'));
  };
  colA.append(sec('Recent jobs', 'sec-recent', recentBox));
  const renderRecent = () => {
    const q = snap.queue || {};
    const inQueue = new Set([q.active?.job_id, ...(q.waiting || []).map((j) => j.job_id)]);
    const list = Array.from(jobs.values()).filter((ev) => !inQueue.has(ev.job_id))
      .sort((a, b) => num(b.unix_ms) - num(a.unix_ms)).slice(0, 20);
    const t = table(['Job', 'Name', 'Revision sent', 'State', 'Bytes', 'When', 'By'], 'jobs recent');
    t.setAttribute('aria-label', 'Recent jobs');
    for (const ev of list) {
      const o = ev.origin || origins.get(ev.job_id) || {};
      const [state, detail] = jobOutcome(ev);
      t.tbody.append(h('tr', { 'data-job': ev.job_id, 'data-state': jobKind(ev) },
        h('td', { class: 'nowrap' }, ev.job_id), h('td', null, o.name || ''), h('td', null, programRef(o.program)),
        h('td', null, h('span', { class: `badge job-${jobKind(ev)}` }, state), detail ? h('div', { class: 'small-text' }, detail) : null),
        h('td', { class: 'num' }, jobBytes(ev)), h('td', null, clock(ev.unix_ms)), h('td', null, who(o.submitted_by))));
    }
    recentBox.replaceChildren(list.length ? scroller(t) : h('p', { class: 'muted' }, 'No recent job.'));
  };

  // ---- send a program
  if (can('job.submit')) colA.append(sec('Send a program', 'sec-send', await submitForm(ctx, cell, base, () => refetch())));

  // ---- DO
  // DO exists in the Protocol A family only; other machines get no form at all.
  const hasDo = can('io.do') && isProtocolA(snap.status?.protocol);
  const doBox = h('div');
  if (hasDo) colB.append(sec('DO output', 'sec-do', doBox));
  let doBuilt = false;
  const renderDo = () => {
    const st = snap.status || {};
    if (!hasDo || doBuilt) return; // built once: keep what the user ticked
    doBuilt = true;
    doBox.replaceChildren(doForm(base, st, (ns) => {
      snap.status = ns;
      schedule('m:status', renderStatus);
    }));
  };

  // ---- alarms
  const alarmList = h('ul', { id: 'alarms', class: 'plain alarms' });
  const alarmEmpty = h('p', { class: 'muted' }, 'No alarm or reset recorded.');
  colB.append(sec('Alarms and resets', 'sec-alarms', alarmEmpty, alarmList,
    can('history.read') ? h('p', { class: 'small-text muted' }, 'The last 24 hours, then live.') : h('p', { class: 'small-text muted' }, 'Live since this page opened.')));
  const alarms = [];
  const alarmKey = (a) => `${a.unix_ms}|${a.kind}|${a.message}`;
  const seen = new Set();
  const addAlarm = (a) => {
    const k = alarmKey(a);
    if (seen.has(k)) return;
    seen.add(k);
    alarms.push(a);
  };
  const renderAlarms = () => {
    alarms.sort((a, b) => num(b.unix_ms) - num(a.unix_ms));
    alarms.length = Math.min(alarms.length, 200);
    alarmList.replaceChildren(...alarms.map((a) => h('li', { 'data-alarm': String(a.unix_ms), class: a.kind === 'ALARM_KIND_CNC_RESET' ? 'reset' : 'alarm' },
      h('time', { datetime: new Date(num(a.unix_ms)).toISOString() }, dateTime(a.unix_ms)), ' ', alarmText(a))));
    alarmEmpty.hidden = alarms.length > 0;
  };
  if (snap.status?.last_alarm) addAlarm(snap.status.last_alarm);
  if (can('history.read')) {
    api('GET', `${cellPath(cell)}/history${query({ machine: name, kind: 'alarm', _time: '[now(-24h)..]', limit: 500 })}`)
      .then((page) => {
        for (const r of page?.records || []) if (r.alarm) addAlarm(r.alarm);
        if (ctx.alive) renderAlarms();
      }).catch(() => {});
  }

  // ---- punched programs
  const punchBox = h('div');
  // Only the Protocol B family punches programs out to the host (§6.1).
  if (!isProtocolA(snap.status?.protocol)) colA.append(sec('Punched programs', 'sec-punched', punchBox));
  const punched = snap.punched || [];
  const renderPunched = () => punchBox.replaceChildren(punchedView(cell, name, punched, !!snap.punched_recorded));

  // ---- G05, where the machine takes G05 streams
  const g05 = g05Panel();
  if (takesG05(cell, name, snap.status)) colB.append(sec('G05 stream', 'sec-g05', g05.el));
  if (snap.status?.g05) g05.push(snap.status.g05);

  // ---- utilisation
  if (can('history.read')) {
    const utilBox = h('div', null, h('p', { class: 'muted' }, 'Loading…'));
    const wide = sec('Utilisation by hour (last 24 h)', 'sec-util', utilBox);
    main.append(wide);
    api('GET', `${cellPath(cell)}/utilisation${query({ machine: name, _time: '[now(-24h)..]', bucket: 'hour' })}`)
      .then((u) => ctx.alive && utilBox.replaceChildren(utilisationView(u, name)))
      .catch(() => utilBox.replaceChildren(h('p', { class: 'muted' }, 'Utilisation could not be read.')));
  }

  const renderAll = () => {
    renderStatus();
    renderQueue();
    renderRecent();
    renderDo();
    renderAlarms();
    renderPunched();
  };
  renderAll();

  // ---- live
  let refetchTimer = 0;
  const refetch = () => {
    clearTimeout(refetchTimer);
    refetchTimer = setTimeout(async () => {
      try {
        const s = await api('GET', base, { quiet: true });
        if (!ctx.alive) return;
        snap = s;
        takeJobs(s.jobs);
        dropEnded(snap.queue);
        punched.splice(0, punched.length, ...(s.punched || []));
        schedule('m:all', renderAll);
      } catch { /* the next event tries again */ }
    }, 600);
  };
  ctx.onCleanup(() => {
    clearTimeout(refetchTimer);
    unschedule('m:');
  });
  const mine = (x) => x && x.machine === name;
  const live = ctx.live(cell, [name], refetch);
  live.on('status', (st) => {
    if (!mine(st)) return;
    const jobChanged = st.current_job_id !== snap.status?.current_job_id || st.jobs_waiting !== snap.status?.jobs_waiting;
    snap.status = st;
    if (st.g05) g05.push(st.g05);
    schedule('m:status', renderStatus);
    schedule('m:do', renderDo);
    if (jobChanged) refetch();
  });
  live.on('job', (ev) => {
    if (!mine(ev)) return;
    if (!isEnd(ev) && ended.has(ev.job_id)) return;
    takeJob(ev);
    if (isEnd(ev)) {
      // The job's end shows at once, everywhere on the page: out of the queue, into the
      // recent jobs with how it ended. The queue is read again to be sure.
      dropEnded(snap.queue);
      schedule('m:status', renderStatus);
      schedule('m:queue', renderQueue);
      schedule('m:recent', renderRecent);
      refetch();
    } else if (ev.progress && activeRefs && activeRefs.id === ev.job_id) {
      schedule('m:progress', () => {
        if (!activeRefs || activeRefs.id !== ev.job_id) return;
        const total = num(ev.progress.bytes_total) || activeRefs.total || 1;
        activeRefs.p.max = total;
        activeRefs.p.value = Math.min(num(ev.progress.bytes_sent), total);
        setText(activeRefs.txt, progressText(num(ev.progress.bytes_sent), total, num(ev.progress.rate_bps)));
        if (ev.progress.block) setText(activeRefs.fed, `fed: ${ev.progress.block}`);
      });
    } else if (!ev.progress) {
      refetch();
    }
  });
  live.on('alarm', (a) => {
    if (!mine(a)) return;
    addAlarm(a);
    schedule('m:alarms', renderAlarms);
  });
  live.on('punch', (p) => {
    if (!mine(p)) return;
    punched.unshift(p);
    schedule('m:punched', renderPunched);
  });
  live.on('di', (d) => {
    if (!mine(d) || !snap.status) return;
    snap.status.di_image = d.value;
    schedule('m:status', renderStatus);
  });
  live.on('g05', (g) => {
    if (mine(g)) g05.push(g);
  });
  live.start();
}

function progressText(sent, total, bps) {
  const pct = total ? Math.floor((100 * Math.min(sent, total)) / total) : 0;
  return ` ${pct}% · ${bytes(sent)} of ${bytes(total)}${bps ? ` · ${rate(bps)}` : ''}`;
}

function programRef(p) {
  if (!p) return '—';
  if (p.library) return `${p.library} rev ${p.revision}`;
  return p.sha256 ? `inline (${p.sha256.slice(0, 12)})` : '—';
}

function jobOutcome(ev) {
  if (ev.completed) return ['completed', `in ${duration(ev.completed.duration_ms)}, ${enumWord(ev.completed.confirmation, 'CONFIRMATION_')}`];
  if (ev.failed) return ['failed', `${ev.failed.alarm_number ? ev.failed.alarm_number + ': ' : ''}${ev.failed.reason}`];
  if (ev.cancelled) return ['cancelled', ev.cancelled.by ? `by ${ev.cancelled.by}` : ''];
  if (ev.progress) return ['sending', ''];
  if (ev.started) return ['started', ''];
  if (ev.queued) return ['queued', `position ${ev.queued.queue_position}`];
  return ['?', ''];
}

function jobBytes(ev) {
  if (ev.completed) return bytes(ev.completed.bytes_sent);
  if (ev.failed) return `${bytes(ev.failed.byte_offset)} acknowledged`;
  if (ev.cancelled) return `${bytes(ev.cancelled.byte_offset)} acknowledged`;
  if (ev.progress) return `${bytes(ev.progress.bytes_sent)} of ${bytes(ev.progress.bytes_total)}`;
  return '';
}

const dl = (pairs) => h('dl', { class: 'kv' }, pairs.filter(Boolean).flatMap(([k, v]) => [h('dt', null, k), h('dd', null, v)]));
const opt = (v, f = (x) => x) => (v == null ? '—' : f(v));

function satView(st) {
  const s = st.sat;
  if (!s) return h('p', { class: 'muted' }, isProtocolA(st.protocol) ? 'No SAT received yet.' : 'No SAT: the Protocol B family has none.');
  const p = s.params || {};
  const digit = (d) => (d == null ? '' : ` (digit ${Number(d).toString(16).toUpperCase()})`);
  const params = table(['Nb', 'No', 'Ne', 'Tp', 'To', 'Ti', 'Tx', 'Tw'], 'params');
  params.setAttribute('aria-label', 'Remote buffer parameters');
  params.tbody.append(h('tr', null, [p.nb, p.no, p.ne, p.tp, p.to, p.ti, p.tx, p.tw].map((v) => h('td', { class: 'num' }, opt(v)))));
  params.append(h('caption', { class: 'small-text' }, 'Parameters: Nb, No bytes · Ne retries · Tp, To, Tw s · Ti, Tx ms'));
  const bufWord = enumWord(s.buffer_status, 'BUFFER_STATUS_');
  return h('div', null, h('h3', null, 'Last SAT'), dl([
    ['Operation', opt(s.remote, (r) => (r ? 'remote' : 'tape'))],
    ['Buffer status', h('span', { class: s.buffer_status === 'BUFFER_STATUS_ALARM' ? 'warn-text' : null }, bufWord + digit(s.buffer_status_digit))],
    // SAT byte 3 means something only in alarm status (§4.4.2): elsewhere it is no cause.
    s.buffer_status === 'BUFFER_STATUS_ALARM' ? ['Alarm cause', h('span', { class: 'warn-text' }, enumWord(s.alarm_cause, 'ALARM_CAUSE_') + digit(s.alarm_cause_digit))] : null,
    ['Bytes buffered', opt(s.bytes_buffered, bytes)],
    // n = 0: the board sends no packets, DATs as in Protocol A (§4.4.2 byte 9).
    ['Packet length', opt(s.packet_n, (n) => (Number(n) === 0 ? 'none (n = 0: DATs, as in Protocol A)' : `${256 * n} bytes (n = ${n})`))],
  ]), scroller(params));
}

function countersView(c) {
  const o = (v) => opt(v, (x) => num(x).toLocaleString());
  return h('div', null, h('h3', null, 'Counters since start'), dl([
    ['Bytes sent / received', `${o(c.bytes_sent)} / ${o(c.bytes_received)}`],
    ['Frames', o(c.frames)],
    ['NC bytes sent', o(c.nc_bytes_sent)],
    ['Jobs completed / failed', `${o(c.jobs_completed)} / ${o(c.jobs_failed)}`],
    ['Retries', o(c.retries)], ['Checksum errors', o(c.checksum_errors)],
    ['Protocol errors', o(c.protocol_errors)], ['Link alarms', o(c.link_alarms)],
    ['Programs punched', o(c.programs_punched)],
  ]));
}

function bitsText(v) {
  if (v == null) return null;
  const bin = (v & 255).toString(2).padStart(8, '0');
  return h('span', { class: 'bits', role: 'img', 'aria-label': `bits 7 to 0: ${bin}` },
    Array.from(bin, (b) => h('i', { class: b === '1' ? 'on' : null }, b)));
}

function ioView(st) {
  if (!isProtocolA(st.protocol)) return null;
  return h('div', null, h('h3', null, 'DI / DO'), dl([
    ['DI (G152)', bitsText(st.di_image) || 'not read yet'],
    ['DO (F152)', bitsText(st.do_image) || 'not output yet'],
  ]));
}

// ---- forms ---------------------------------------------------------------------------

async function submitForm(ctx, cell, base, after) {
  let programSel;
  if (can('program.read') || can('program.write')) {
    let list = [];
    try {
      list = (await api('GET', `${cellPath(cell)}/programs`)) || [];
    } catch { /* shown */ }
    programSel = select('submit-program', [['', '— choose —'], ...list.map((p) => [p.name, p.name])]);
  } else {
    programSel = h('input', { id: 'submit-program', autocomplete: 'off' }); // cannot list: type the name
  }
  const revSel = select('submit-revision', [['', 'latest']]);
  const prio = h('input', { id: 'submit-priority', type: 'number', value: '0', step: '1', inputmode: 'numeric' });
  const jobName = h('input', { id: 'submit-name', autocomplete: 'off' });
  const btn = h('button', { type: 'submit', id: 'submit-submit' }, 'Send');
  if (programSel.tagName === 'SELECT') {
    programSel.addEventListener('change', () => fillRevisions(cell, programSel.value, revSel));
  }
  const form = h('form', { class: 'stack' }, field('Library program', programSel), field('Revision', revSel),
    h('div', { class: 'row' }, field('Priority', prio), field('Job name (optional)', jobName)), h('div', { class: 'actions' }, btn));
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    if (!programSel.value) {
      programSel.focus();
      return;
    }
    act(btn, async () => {
      const a = await api('POST', `${base}/submit`, { json: { library: programSel.value, revision: revSel.value, priority: Number(prio.value) || 0, name: jobName.value } });
      notice(`Job ${a.job_id} accepted (${programRef(a.program)}), ${a.queue_position} ahead of it.`);
      after();
    });
  });
  return form;
}

export async function fillRevisions(cell, program, revSel, value = '') {
  revSel.replaceChildren(h('option', { value: '' }, 'latest'));
  if (!program || !(can('program.read') || can('program.write'))) return;
  try {
    const r = await api('GET', `${cellPath(cell)}/programs/${enc(program)}/revisions`);
    for (const x of r.revisions || []) {
      revSel.append(h('option', { value: String(x.number), selected: String(x.number) === String(value) },
        `${x.number} · ${revState(x.state)} · ${dateTime(x.unix_ms)}`));
    }
  } catch { /* shown */ }
}

function doForm(base, st, done) {
  const cur = st.do_image ?? 0;
  const val = [];
  const mask = [];
  const t = table(['', ...[7, 6, 5, 4, 3, 2, 1, 0].map((b) => `Bit ${b}`)], 'do-bits');
  t.setAttribute('aria-label', 'DO bits');
  const valueRow = h('tr', null, h('th', { scope: 'row' }, 'Output'));
  const maskRow = h('tr', null, h('th', { scope: 'row' }, 'Change'));
  for (let b = 7; b >= 0; b--) {
    const v = h('input', { type: 'checkbox', id: `do-value-${b}`, checked: (cur >> b) & 1 ? true : null });
    const m = h('input', { type: 'checkbox', id: `do-mask-${b}`, checked: true });
    val[b] = v;
    mask[b] = m;
    valueRow.append(h('td', null, h('label', { for: v.id, class: 'bitcheck' }, v, h('span', { class: 'sr-only' }, `DO bit ${b} on`))));
    maskRow.append(h('td', null, h('label', { for: m.id, class: 'bitcheck' }, m, h('span', { class: 'sr-only' }, `change DO bit ${b}`))));
  }
  t.tbody.append(valueRow, maskRow);
  const btn = h('button', { type: 'submit', id: 'do-submit' }, 'Output DO');
  const form = h('form', { class: 'stack' }, h('p', { class: 'small-text muted' }, 'Ticked “Output” bits go out as 1; only bits ticked “Change” are changed.'), scroller(t), h('div', { class: 'actions' }, btn));
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    let value = 0;
    let m = 0;
    for (let b = 0; b < 8; b++) {
      if (val[b].checked) value |= 1 << b;
      if (mask[b].checked) m |= 1 << b;
    }
    act(btn, async () => {
      const ns = await api('POST', `${base}/do`, { json: { value, mask: m } });
      notice(`DO 0x${value.toString(16).padStart(2, '0')} (mask 0x${m.toString(16).padStart(2, '0')}) output.`);
      if (ns && ns.machine) done(ns);
    });
  });
  return form;
}

// ---- punched programs ----------------------------------------------------------------

function comparisonText(p) {
  if (p.damaged) return `damaged: ${p.damage}`;
  if (p.request) {
    const r = p.request;
    return `remote request ${r.program}: ${r.error ? r.error : `job ${r.job_id} (${r.library_name})`}`;
  }
  const c = p.comparison;
  if (!c) return 'not compared (no O-number or no such library program)';
  if (c.same) return `same as ${c.library_name} rev ${c.revision}`;
  return `${c.blocks_changed} changed, ${c.blocks_added} added, ${c.blocks_removed} removed against ${c.library_name} rev ${c.revision}`;
}

// The list comes from the cell's history (30 days) where the user may read it; else only
// what the console saw since it started. Either way the programs are in the library.
function punchedNote(cell, machine, recorded) {
  const library = h('a', { href: `#/cell/${enc(cell)}/programs` }, 'library');
  if (recorded) {
    return h('p', { class: 'small-text muted', 'data-field': 'punched-note' },
      'Punched in the last 30 days, as the cell\'s history keeps them. Their text is in the ', library, ` as ${machine}-O…-time.`);
  }
  return h('p', { class: 'small-text muted', 'data-field': 'punched-note' },
    'Your roles do not read the history: this list holds what the console saw since it started. Programs punched before are in the ',
    library, ` as ${machine}-O…-time: adopted as a revision of their program, they compare with it there.`);
}

function punchedView(cell, machine, list, recorded) {
  if (!list.length) return h('div', null, h('p', { class: 'muted' }, recorded ? 'Nothing punched in the last 30 days.' : 'Nothing punched since the console started.'), punchedNote(cell, machine, recorded));
  const t = table(['When', 'Program', 'Stored as', 'Against the library', ''], 'punched');
  t.setAttribute('aria-label', 'Punched programs');
  for (const p of list.slice(0, 50)) {
    const c = p.comparison;
    let adopt = null;
    if (can('program.write') && c && !c.same && p.library_name && !p.damaged) {
      adopt = h('button', { type: 'button', class: 'small', 'data-action': 'adopt',
        onclick: (e) => act(e.currentTarget, async () => {
          const info = await api('POST', `${cellPath(cell)}/programs/${enc(c.library_name)}/adopt`,
            { json: { from: p.library_name, revision: '', comment: `adopted from ${machine}'s punch of ${dateTime(p.unix_ms)}` } });
          notice(`${info.name} has a new revision ${info.latest?.number ?? ''} from ${p.library_name}.`);
        }) }, `Adopt as revision of ${c.library_name}`);
    }
    const text = b64text(p.program);
    t.tbody.append(h('tr', { 'data-punch': String(p.unix_ms), class: p.damaged ? 'bad' : null },
      h('td', null, dateTime(p.unix_ms)),
      h('td', null, p.name, p.o_number && p.o_number !== p.name ? ` (${p.o_number})` : '', h('div', { class: 'small-text muted' }, enumWord(p.code_system, 'CODE_SYSTEM_'))),
      h('td', null, p.library_name || '—'),
      h('td', { 'data-field': 'comparison' }, comparisonText(p)),
      h('td', null, adopt, text ? h('details', null, h('summary', null, 'Text'), h('pre', { class: 'code small' }, text)) : null)));
  }
  return h('div', null, scroller(t), punchedNote(cell, machine, recorded));
}

// ---- G05 -----------------------------------------------------------------------------

const MAX_POINTS = 600;

function g05Panel() {
  const info = h('div');
  const blocks = lineChart('Blocks', [['cnc_buffer', 'CNC buffer (blocks)', 's1'], ['credits', 'Credits (blocks)', 's2']]);
  const under = lineChart('Underruns', [['underruns', 'Underruns (estimated, total)', 's3']]);
  const charts = h('div', { hidden: true }, blocks.el, under.el);
  const el = h('div', null, info, charts);
  info.append(h('p', { class: 'muted' }, 'No G05 stream since the gateway started.'));
  let stream = null;
  return {
    el,
    push(g) {
      if (!g || !g.stream_id) return;
      if (stream !== g.stream_id) {
        stream = g.stream_id;
        blocks.reset();
        under.reset();
      }
      const t = num(g.unix_ms) || Date.now();
      blocks.add(t, { cnc_buffer: num(g.cnc_buffer), credits: num(g.credits) });
      under.add(t, { underruns: num(g.underruns) });
      schedule('m:g05', () => {
        charts.hidden = false;
        info.replaceChildren(dl([
          ['Stream', `${g.stream_id} · ${enumWord(g.state, 'G05_STATE_')}${g.end_reason && g.end_reason !== 'G05_END_REASON_UNSPECIFIED' ? ` (${enumWord(g.end_reason, 'G05_END_REASON_')})` : ''}`],
          ['Blocks received / on line', `${num(g.received)} / ${num(g.on_line)}`],
          ['Gaps / repeats / refused', `${num(g.gaps)} / ${num(g.repeats)} / ${num(g.refused)}`],
          g.last_error ? ['Last error', g.last_error] : null,
        ]));
        blocks.render();
        under.render();
      });
    },
  };
}

// A small multi-line chart over time: one polyline per series, the legend gives each
// series' name and current value in text (colour and dash differ too).
function lineChart(title, series) {
  const W = 600;
  const H = 120;
  const data = [];
  const lines = series.map(([, , cls]) => svg('polyline', { class: `line ${cls}`, fill: 'none', 'vector-effect': 'non-scaling-stroke' }));
  const chart = svg('svg', { class: 'chart', viewBox: `0 0 ${W} ${H}`, preserveAspectRatio: 'none', role: 'img', 'aria-label': title }, lines);
  const legend = h('ul', { class: 'legend plain' });
  const scale = h('span', { class: 'small-text muted' });
  const el = h('figure', { class: 'chart-box' }, h('figcaption', null, title, ' ', scale), chart, legend);
  return {
    el,
    reset() { data.length = 0; },
    add(t, values) {
      data.push([t, values]);
      if (data.length > MAX_POINTS) data.splice(0, data.length - MAX_POINTS);
    },
    render() {
      if (!data.length) return;
      const [x0, x1] = [data[0][0], data[data.length - 1][0]];
      const [, hi] = extent(data.flatMap(([, v]) => series.map(([k]) => v[k])));
      series.forEach(([k], i) => lines[i].setAttribute('points', polyPoints(data.map(([t, v]) => [t, v[k]]), W, H, x0, x1, 0, Math.max(1, hi))));
      setText(scale, `(0 to ${Math.max(1, hi)}, last ${duration(x1 - x0)})`);
      const last = data[data.length - 1][1];
      legend.replaceChildren(...series.map(([k, label, cls]) => h('li', null, h('span', { class: `swatch ${cls}`, 'aria-hidden': 'true' }), `${label}: ${last[k]}`)));
    },
  };
}

// ---- utilisation ---------------------------------------------------------------------

const UTIL = [
  ['reading', 'Reading', (b) => num(b.reading_ms) + num(b.punching_ms)],
  ['idle', 'Idle', (b) => num(b.idle_ms)],
  ['alarm', 'Alarm + reset', (b) => num(b.alarm_ms) + num(b.reset_ms)],
  ['down', 'Link down', (b) => num(b.link_down_ms)],
  ['unknown', 'Unknown', (b) => num(b.unknown_ms)],
];

// An axis label is a time of day (`14:00`), not a duration (`14h`).
const hourOfDay = (ms) => `${String(new Date(num(ms)).getHours()).padStart(2, '0')}:00`;

function utilisationView(u, name) {
  const m = (u?.machines || []).find((x) => x.machine === name) || u?.machines?.[0];
  if (!m || !m.buckets?.length) return h('p', { class: 'muted' }, 'No utilisation recorded yet.');
  const bs = m.buckets;
  const BW = 24;
  const H = 120;
  const TOP = 14;
  const BOTTOM = 16;
  const chart = svg('svg', { class: 'util', viewBox: `0 0 ${bs.length * BW} ${H + TOP + BOTTOM}`, role: 'img',
    'aria-label': `Utilisation of ${name} per ${u.bucket || 'hour'}; the table below gives the figures` });
  bs.forEach((b, i) => {
    const len = Math.max(1, num(b.end_unix_ms) - num(b.start_unix_ms));
    let y = TOP + H;
    for (const [key, label, f] of UTIL) {
      const ms = f(b);
      if (!ms) continue;
      const hh = (H * ms) / len;
      y -= hh;
      chart.append(svg('rect', { x: i * BW + 2, y: y.toFixed(1), width: BW - 4, height: hh.toFixed(1), class: `u-${key}` },
        svg('title', null, `${clock(b.start_unix_ms)}: ${label} ${Math.round((100 * ms) / len)}%`)));
    }
    if (b.parts != null) chart.append(svg('text', { x: i * BW + BW / 2, y: TOP - 3, class: 'parts', 'text-anchor': 'middle' }, String(Math.round(b.parts))));
    if (i % 3 === 0) chart.append(svg('text', { x: i * BW + BW / 2, y: TOP + H + 12, class: 'hour', 'text-anchor': 'middle' }, hourOfDay(b.start_unix_ms)));
  });
  const legend = h('ul', { class: 'legend plain' }, UTIL.map(([k, l]) => h('li', null, h('span', { class: `swatch u-${k}`, 'aria-hidden': 'true' }), l)),
    bs.some((b) => b.parts != null) ? h('li', null, 'Numbers above the bars: parts made') : null);
  const t = table(['From', ...UTIL.map(([, l]) => l), 'Parts', 'Jobs ok / failed'], 'util-table');
  t.setAttribute('aria-label', 'Utilisation figures');
  for (const b of bs) {
    // Shares of the time that has passed: the current bucket has not ended yet.
    const len = Math.max(1, UTIL.reduce((sum, [, , f]) => sum + f(b), 0));
    t.tbody.append(h('tr', null, h('td', null, clock(b.start_unix_ms)),
      UTIL.map(([, , f]) => h('td', { class: 'num' }, `${Math.round((100 * f(b)) / len)}%`)),
      h('td', { class: 'num' }, b.parts == null ? '—' : Math.round(b.parts)), h('td', { class: 'num' }, `${b.jobs_completed} / ${b.jobs_failed}`)));
  }
  return h('div', null, h('div', { class: 'util-scroll' }, chart), legend,
    m.part_counter ? h('p', { class: 'small-text muted' }, `Parts from ${m.part_counter}.`) : null,
    h('details', null, h('summary', null, 'Figures as a table'), scroller(t)));
}

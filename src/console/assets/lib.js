// Shared helpers: DOM building, the JSON API, alerts, formatting, render batching,
// live events and small SVG charts. No dependencies.

export const state = { me: null, perms: new Set(), cells: [] };
export const can = (p) => state.perms.has(p);

export const cellNames = () => state.cells.map((c) => c.cell);
// The cell's machine and PLC names; a list of objects is taken too (the docs leave it open).
const names = (list) => (list || []).map((x) => (typeof x === 'string' ? x : x.machine || x.plc || x.name));
export const cellInfo = (cell) => state.cells.find((c) => c.cell === cell);
export const machinesOf = (cell) => names(cellInfo(cell)?.machines);
export const plcsOf = (cell) => names(cellInfo(cell)?.plcs);
// Whether a machine takes G05 streams (its cell file has a g05 table), or showed one.
export const takesG05 = (cell, machine, status) => !!status?.g05 || (cellInfo(cell)?.g05 || []).includes(machine);

// ---- DOM ----------------------------------------------------------------------------

export const $ = (sel, root = document) => root.querySelector(sel);
export const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));

// h('tag', {attr: value, onclick: fn, text: '...'}, ...children): attributes are set
// with setAttribute so the markup tests see matches what we meant; null/false skip.
export function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  if (attrs) {
    for (const [k, v] of Object.entries(attrs)) {
      if (v == null || v === false) continue;
      if (k === 'class') el.className = v;
      else if (k === 'text') el.textContent = v;
      else if (k.startsWith('on') && typeof v === 'function') el.addEventListener(k.slice(2), v);
      else el.setAttribute(k, v === true ? '' : String(v));
    }
  }
  append(el, children);
  return el;
}

export function append(el, children) {
  for (const c of children.flat(Infinity)) {
    if (c == null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

// replaceChildren that skips null/false children as h() does.
export function fill(el, ...children) {
  el.replaceChildren();
  return append(el, children);
}

// Set text only when it changed: live updates touch the DOM as little as they can.
export function setText(el, text) {
  text = text == null ? '' : String(text);
  if (el && el.textContent !== text) el.textContent = text;
}

let uid = 0;
export const nextId = (p = 'f') => `${p}-${++uid}`;

// A labelled form field: returns the wrapper; the control is field.control.
export function field(label, control, hint) {
  if (!control.id) control.id = nextId();
  const wrap = h('div', { class: 'field' }, h('label', { for: control.id }, label), control,
    hint ? h('span', { class: 'hint' }, hint) : null);
  wrap.control = control;
  return wrap;
}

export function select(id, options, value) {
  const s = h('select', { id });
  for (const o of options) {
    const [v, t] = Array.isArray(o) ? o : [o, o];
    const opt = h('option', { value: v }, t);
    if (String(v) === String(value)) opt.selected = true;
    s.append(opt);
  }
  return s;
}

export function table(headers, cls) {
  const tbody = h('tbody');
  const t = h('table', { class: cls || null },
    h('thead', null, h('tr', null, headers.map((x) => h('th', { scope: 'col' }, x)))), tbody);
  t.tbody = tbody;
  return t;
}

// Tables scroll sideways inside their own box on narrow screens.
export const scroller = (el) => h('div', { class: 'scroll', tabindex: '0', role: 'region',
  'aria-label': el.getAttribute('aria-label') || el.caption?.textContent || 'table' }, el);

// ---- alerts --------------------------------------------------------------------------

// Errors go to #alerts (role=alert); the same text again bumps a counter, not a new box.
export function alertError(message, detail) {
  const box = $('#alerts');
  if (!box) return;
  const key = message + '|' + (detail || '');
  const old = $$('.alert', box).find((a) => a.dataset.key === key);
  if (old) {
    const n = Number(old.dataset.count || 1) + 1;
    old.dataset.count = n;
    setText($('.count', old), `(${n}×)`);
    return;
  }
  const item = h('div', { class: 'alert error', 'data-key': key, 'data-time': String(Date.now()) },
    h('p', { class: 'msg' }, h('strong', null, 'Error: '), message, ' ', h('span', { class: 'count' })),
    detail ? h('p', { class: 'detail' }, detail) : null,
    h('button', { type: 'button', class: 'small', onclick: () => item.remove() }, 'Dismiss'));
  box.append(item);
  const all = $$('.alert', box);
  if (all.length > 6) all[0].remove();
}

export function notice(message) {
  const box = $('#notices');
  if (!box) return;
  const item = h('div', { class: 'alert ok', 'data-time': String(Date.now()) }, h('p', null, message),
    h('button', { type: 'button', class: 'small', onclick: () => item.remove() }, 'Dismiss'));
  box.append(item);
  setTimeout(() => item.remove(), 8000);
}

// olderThan: keep what was shown in the last moment (an error that led to this page).
export function clearAlerts(olderThan = 0) {
  for (const a of $$('#alerts .alert, #notices .alert')) {
    if (!olderThan || Date.now() - Number(a.dataset.time || 0) > olderThan) a.remove();
  }
}

// ---- API -----------------------------------------------------------------------------

export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

let onUnauthorized = () => {};
export const setUnauthorizedHandler = (fn) => { onUnauthorized = fn; };

export const enc = encodeURIComponent;
export const cellPath = (cell) => `/cells/${enc(cell)}`;

// api('GET', '/cells') → parsed JSON (or text for text/plain); throws ApiError after
// showing its message unless opts.quiet. 401 hands over to the login page.
export async function api(method, path, opts = {}) {
  const headers = {};
  let body = opts.body;
  if (opts.json !== undefined) {
    headers['Content-Type'] = 'application/json';
    body = JSON.stringify(opts.json);
  } else if (body !== undefined) {
    headers['Content-Type'] = 'application/octet-stream';
  }
  if (method !== 'GET' && state.me?.csrf) headers['X-CSRF-Token'] = state.me.csrf;
  let res;
  try {
    res = await fetch('/api/v1' + path, { method, headers, body, credentials: 'same-origin', cache: 'no-store' });
  } catch (e) {
    const err = new ApiError(0, 'NETWORK', `The console did not answer (${method} ${path}): ${e.message}`);
    if (!opts.quiet) alertError(err.message);
    throw err;
  }
  if (res.status === 401 && !opts.noRedirect) {
    const err = new ApiError(401, 'UNAUTHENTICATED', 'Not logged in');
    onUnauthorized(err);
    throw err;
  }
  if (!res.ok) {
    let code = `HTTP_${res.status}`;
    let message = `${method} ${path} answered ${res.status} ${res.statusText}`;
    try {
      const j = await res.json();
      if (j && j.message) message = j.message;
      if (j && j.code) code = j.code;
    } catch { /* not JSON: keep the status line */ }
    const err = new ApiError(res.status, code, message);
    if (!opts.quiet) alertError(message, `${code.replace(/^ERROR_CODE_/, '')} · HTTP ${res.status}`);
    throw err;
  }
  const text = await res.text();
  if (opts.text) return text;
  if (!text) return null;
  const ct = res.headers.get('content-type') || '';
  if (!ct.includes('json')) return text;
  try {
    return JSON.parse(text);
  } catch (e) {
    const err = new ApiError(res.status, 'BAD_JSON', `${method} ${path}: unreadable answer (${e.message})`);
    if (!opts.quiet) alertError(err.message);
    throw err;
  }
}

// Query string from an object; empty values are left out. Values are percent-encoded.
export function query(params) {
  const parts = [];
  for (const [k, v] of Object.entries(params)) {
    if (v == null || v === '') continue;
    parts.push(`${enc(k)}=${enc(v)}`);
  }
  return parts.length ? '?' + parts.join('&') : '';
}

// Run an action from a button or form: disables it while under way; errors are already
// shown by api(), others are shown here.
export async function act(button, fn) {
  if (button) button.disabled = true;
  try {
    return await fn();
  } catch (e) {
    if (!(e instanceof ApiError)) alertError(e.message || String(e));
    return undefined;
  } finally {
    if (button) button.disabled = false;
  }
}

// ---- formatting ----------------------------------------------------------------------

// 64-bit integers arrive as strings.
export const num = (x) => (x == null || x === '' ? 0 : Number(x));

// As the command line writes sizes: bytes, then KiB, MiB, GiB.
export function bytes(n) {
  n = num(n);
  const K = 1024;
  if (n < K) return `${n} B`;
  if (n < K * K) return `${(n / K).toFixed(1)} KiB`;
  if (n < K * K * K) return `${(n / (K * K)).toFixed(1)} MiB`;
  return `${(n / (K * K * K)).toFixed(1)} GiB`;
}

export const rate = (bps) => `${bytes(bps)}/s`;

const pad = (n, w = 2) => String(n).padStart(w, '0');

export function dateTime(ms) {
  ms = num(ms);
  if (!ms) return '—';
  const d = new Date(ms);
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

export function clock(ms) {
  ms = num(ms);
  if (!ms) return '—';
  const d = new Date(ms);
  const today = new Date();
  if (d.toDateString() !== today.toDateString()) return dateTime(ms);
  return `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

export function duration(ms) {
  ms = num(ms);
  if (ms < 1000) return `${ms} ms`;
  const s = Math.round(ms / 1000);
  if (s < 120) return `${s} s`;
  const m = Math.floor(s / 60);
  if (m < 120) return `${m} min ${s % 60} s`;
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

// "LINK_STATE_SENDING" → "sending" (prefix given), for people.
export function enumWord(v, prefix) {
  if (v == null || v === '') return '';
  let s = String(v);
  if (prefix && s.startsWith(prefix)) s = s.slice(prefix.length);
  return s.toLowerCase().replace(/_/g, ' ');
}

export const linkWord = (s) => (s ? String(s).replace(/^LINK_STATE_/, '') : 'UNSPECIFIED');

export const PROTOCOL = {
  PROTOCOL_A: 'Protocol A',
  PROTOCOL_EXPANSION_A: 'Expansion A',
  PROTOCOL_B: 'Protocol B',
  PROTOCOL_EXPANSION_B: 'Expansion B',
};
export const protocolName = (p) => PROTOCOL[p] || enumWord(p, 'PROTOCOL_') || '—';
export const isProtocolA = (p) => p === 'PROTOCOL_A' || p === 'PROTOCOL_EXPANSION_A';
// A link is up while the remote buffer answers: in alarm too (it answers with its alarm),
// which is counted apart as the machine's state, not as a link lost.
export const linkUp = (s) => s === 'LINK_STATE_IDLE' || s === 'LINK_STATE_SENDING' || s === 'LINK_STATE_RECEIVING' || s === 'LINK_STATE_ALARM';
export const inAlarm = (s) => s === 'LINK_STATE_ALARM';
// Whether an AlarmEvent reports an alarm (a reset reports the end of one).
export const isAlarm = (a) => !!a && a.kind !== 'ALARM_KIND_CNC_RESET';

export function who(o) {
  if (!o || (!o.user && !o.via)) return '—';
  if (!o.via) return o.user;
  if (!o.user) return `(${o.via})`;
  return `${o.user} (${o.via})`;
}

export function alarmText(a) {
  if (!a) return '';
  const kind = { ALARM_KIND_CNC_ALARM: 'CNC alarm', ALARM_KIND_CNC_RESET: 'CNC reset',
    ALARM_KIND_LINK_ALARM: 'Link alarm', ALARM_KIND_REMOTE_REQUEST: 'Remote request' }[a.kind] || 'Alarm';
  return `${kind}${a.alarm_number ? ' ' + a.alarm_number : ''}: ${a.message}`;
}

export function revState(s) {
  return enumWord(s, 'REVISION_STATE_') || '—';
}

// The one set member of a proto3 oneof, as [name, value].
export function oneof(obj, names) {
  for (const n of names) if (obj && obj[n] != null) return [n, obj[n]];
  return [null, null];
}
export const JOB_KINDS = ['queued', 'started', 'progress', 'completed', 'failed', 'cancelled'];
export const jobKind = (ev) => oneof(ev, JOB_KINDS)[0];

// Base64 (proto3 JSON bytes) → text; NC programs are 7-bit ASCII.
export function b64text(b64) {
  if (!b64) return '';
  try {
    const bin = atob(b64);
    const u8 = Uint8Array.from(bin, (c) => c.charCodeAt(0));
    return new TextDecoder('latin1').decode(u8);
  } catch {
    return '';
  }
}

// ---- render batching -----------------------------------------------------------------

// Live events change models at once; their DOM work is queued by key (latest wins) and run
// in one animation frame at most ~4 times a second.
const pending = new Map();
let timer = 0;
let lastFlush = 0;
const MIN_GAP_MS = 250;

export function schedule(key, fn) {
  pending.set(key, fn);
  if (timer) return;
  const wait = Math.max(0, MIN_GAP_MS - (performance.now() - lastFlush));
  timer = setTimeout(() => requestAnimationFrame(flush), wait);
}

function flush() {
  timer = 0;
  lastFlush = performance.now();
  const fns = Array.from(pending.values());
  pending.clear();
  for (const fn of fns) {
    try {
      fn();
    } catch (e) {
      console.error(e);
    }
  }
}

export function unschedule(prefix) {
  for (const k of Array.from(pending.keys())) if (k.startsWith(prefix)) pending.delete(k);
}

// ---- live events ---------------------------------------------------------------------

const lives = new Set();
let connListener = () => {};
export const onConnectionChange = (fn) => { connListener = fn; };

function connSummary() {
  const all = Array.from(lives);
  // A page without an event stream is not a lost connection: say what it is.
  if (!all.length) return { state: 'none', text: 'Not live', title: 'This page shows what it read when it opened and does not update by itself: reload it for the latest.' };
  if (all.every((l) => l.open)) return { state: 'ok', text: 'Live: connected', title: 'This page updates as the cell publishes.' };
  const next = Math.min(...all.filter((l) => !l.open).map((l) => l.retryAt || Date.now()));
  const s = Math.max(0, Math.round((next - Date.now()) / 1000));
  return { state: 'bad', text: s > 0 ? `Live: reconnecting in ${s} s` : 'Live: connecting…', title: 'The page lost its event stream: what it shows may be out of date until it is back.' };
}
export const connectionChanged = () => connListener(connSummary());

const EVENT_TYPES = ['status', 'job', 'alarm', 'punch', 'di', 'tag', 'plc', 'g05'];

// One EventSource on a cell's events, reconnected with exponential backoff. onResync runs
// each time the stream opens, the first time too: a page reads what it shows before its
// stream is open, and what happened in between (a job started) would be missed.
export class Live {
  constructor(cell, machines, onResync) {
    this.cell = cell;
    this.machines = machines || [];
    this.onResync = onResync;
    this.handlers = {};
    this.open = false;
    this.delay = 1000;
    this.failures = 0;
    this.closed = false;
  }
  on(type, fn) {
    (this.handlers[type] ||= []).push(fn);
    return this;
  }
  start() {
    lives.add(this);
    this.connect();
    return this;
  }
  connect() {
    if (this.closed) return;
    const q = this.machines.map((m) => `machine=${enc(m)}`).join('&');
    const es = new EventSource(`/api/v1${cellPath(this.cell)}/events${q ? '?' + q : ''}`);
    this.es = es;
    es.onopen = () => {
      this.open = true;
      this.retryAt = 0;
      connectionChanged();
      if (this.onResync) this.onResync();
    };
    es.onerror = () => {
      es.close();
      if (this.closed) return;
      this.open = false;
      this.failures++;
      const wait = this.delay + Math.random() * 500;
      this.delay = Math.min(this.delay * 2, 30000);
      this.retryAt = Date.now() + wait;
      connectionChanged();
      clearInterval(this.tick);
      this.tick = setInterval(connectionChanged, 1000);
      this.timer = setTimeout(() => {
        clearInterval(this.tick);
        this.connect();
      }, wait);
      // A stream refused for a lost session looks like any error: ask /me.
      if (this.failures % 3 === 1) api('GET', '/me', { quiet: true }).catch(() => {});
    };
    // The console says the page fell behind its events: reload what it shows.
    es.addEventListener('resync', () => {
      if (this.onResync) this.onResync();
    });
    for (const t of EVENT_TYPES) {
      es.addEventListener(t, (e) => {
        this.delay = 1000;
        const fns = this.handlers[t];
        if (!fns) return;
        let msg;
        try {
          msg = JSON.parse(e.data);
        } catch {
          console.warn('unreadable event', t, e.data);
          return;
        }
        for (const fn of fns) fn(msg);
      });
    }
  }
  close() {
    this.closed = true;
    clearTimeout(this.timer);
    clearInterval(this.tick);
    if (this.es) this.es.close();
    lives.delete(this);
    connectionChanged();
  }
}

// ---- SVG charts ----------------------------------------------------------------------

const SVG = 'http://www.w3.org/2000/svg'; // the SVG namespace name, not a request
export function svg(tag, attrs, ...children) {
  const el = document.createElementNS(SVG, tag);
  if (attrs) for (const [k, v] of Object.entries(attrs)) if (v != null) el.setAttribute(k, String(v));
  for (const c of children.flat()) if (c != null) el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return el;
}

// Polyline points for [[x, y], ...] scaled into w×h (y up). Flat data sits mid-height.
export function polyPoints(points, w, h, x0, x1, y0, y1) {
  if (!points.length) return '';
  if (x1 <= x0) x1 = x0 + 1;
  if (y1 <= y0) {
    y0 -= 1;
    y1 += 1;
  }
  const sx = w / (x1 - x0);
  const sy = (h - 2) / (y1 - y0);
  let out = '';
  for (const [x, y] of points) {
    out += `${((x - x0) * sx).toFixed(1)},${(h - 1 - (y - y0) * sy).toFixed(1)} `;
  }
  return out.trim();
}

export function extent(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (v < lo) lo = v;
    if (v > hi) hi = v;
  }
  return lo === Infinity ? [0, 1] : [lo, hi];
}

// The console's entry: session, top bar, hash router, login page.
import {
  $, h, api, state, can, setText, field, alertError, clearAlerts, notice, act, enc,
  setUnauthorizedHandler, onConnectionChange, connectionChanged, Live, ApiError,
  cellNames, plcsOf,
} from './lib.js';
import { renderOverview } from './overview.js';
import { renderMachine } from './machine.js';
import { renderPrograms, renderProgram } from './programs.js';
import { renderPlc } from './plc.js';
import { renderHistory } from './history.js';

let returnTo = '';
let current = null; // the page shown: its cleanups and liveness

setUnauthorizedHandler(() => {
  const wasIn = !!state.me;
  state.me = null;
  state.perms = new Set();
  if (!location.hash.startsWith('#/login')) returnTo = location.hash;
  if (wasIn) alertError('Your session ended: log in again.');
  renderTopbar();
  if (!location.hash.startsWith('#/login')) location.hash = '#/login';
  else route();
});

function setMe(me) {
  state.me = me;
  state.perms = new Set(me.permissions || []);
}

async function loadCells() {
  state.cells = (await api('GET', '/cells')) || [];
}


// ---- top bar -------------------------------------------------------------------------

function routeCell() {
  const m = /^#\/cell\/([^/?]+)/.exec(location.hash);
  return m ? decodeURIComponent(m[1]) : null;
}

let navCell = null;

function renderTopbar() {
  const nav = $('#nav');
  const user = $('#user');
  nav.replaceChildren();
  user.replaceChildren();
  const cells = cellNames();
  setText($('#cell-names'), cells.length ? cells.join(', ') : '');
  $('#conn').hidden = !state.me;
  if (!state.me) return;
  navCell = routeCell() || (cells.includes(navCell) ? navCell : cells[0]);
  const here = location.hash || '#/';
  const link = (href, text) => h('a', { href, 'aria-current': here === href || (href !== '#/' && here.startsWith(href + '?')) ? 'page' : null }, text);
  const items = [link('#/', 'Overview')];
  if (navCell) {
    if (cells.length > 1) {
      const sel = h('select', { id: 'nav-cell' }, cells.map((c) => h('option', { value: c, selected: c === navCell }, c)));
      sel.addEventListener('change', () => {
        const old = navCell;
        navCell = sel.value;
        const rc = routeCell();
        if (rc && rc === old) location.hash = location.hash.replace(`#/cell/${enc(old)}`, `#/cell/${enc(navCell)}`);
        else {
          renderTopbar();
          $('#nav-cell')?.focus(); // the select was rebuilt: keep the keyboard where it was
        }
      });
      items.push(h('span', { class: 'nav-cell' }, h('label', { for: 'nav-cell' }, 'Cell'), sel));
    }
    const base = `#/cell/${enc(navCell)}`;
    if (can('program.read') || can('program.write')) items.push(link(`${base}/programs`, 'Programs'));
    if (can('status.read')) for (const p of plcsOf(navCell)) items.push(link(`${base}/plc/${enc(p)}`, `PLC ${p}`));
    if (can('history.read') || can('audit.read')) items.push(link(`${base}/history`, 'History'));
  }
  // The cell's MTConnect agent, where the gateway serves one (docs/mtconnect.md).
  if (state.me.mtconnect && can('status.read')) {
    items.push(h('a', { href: `${state.me.mtconnect}current`, id: 'mtconnect', rel: 'noopener' }, 'MTConnect'));
  }
  nav.append(...items);
  // Only a password login can be ended: a console without users has none, and a client
  // certificate logs the browser in again at once.
  if (state.me.via === 'none') {
    user.append(h('span', { class: 'who muted', id: 'no-login', title: 'This console has no users: anyone who reaches it may do everything (docs/console.md, Who may do what).' }, 'No login'));
    return;
  }
  user.append(h('span', { class: 'who', title: state.me.via ? `via ${state.me.via}` : null }, state.me.user || '(anonymous)'),
    state.me.via === 'password' ? h('button', { type: 'button', class: 'small', id: 'logout', onclick: (e) => logout(e.currentTarget) }, 'Log out') : null);
}

async function logout(btn) {
  await act(btn, async () => {
    await api('POST', '/logout');
    state.me = null;
    state.perms = new Set();
    returnTo = '';
    notice('Logged out.');
    location.hash = '#/login';
    renderTopbar();
  });
}

onConnectionChange(({ state: s, text, title }) => {
  const el = $('#conn');
  el.dataset.state = s;
  el.title = title || '';
  setText($('.conn-text', el), text);
});

// ---- router --------------------------------------------------------------------------

function parseHash() {
  const raw = location.hash.replace(/^#/, '') || '/';
  const [path, qs] = raw.split('?');
  const parts = path.split('/').filter(Boolean).map((p) => {
    try {
      return decodeURIComponent(p);
    } catch {
      return p;
    }
  });
  return { parts, params: new URLSearchParams(qs || '') };
}

function makeContext(main) {
  const ctx = {
    main,
    alive: true,
    cleanups: [],
    onCleanup(fn) { this.cleanups.push(fn); },
    // A live stream closed with the page.
    live(cell, machines, onResync) {
      const l = new Live(cell, machines, onResync);
      this.onCleanup(() => l.close());
      return l;
    },
    title(t) {
      document.title = `${t} · cellgate`;
    },
  };
  return ctx;
}

async function route() {
  if (current) {
    current.alive = false;
    for (const fn of current.cleanups) {
      try { fn(); } catch (e) { console.error(e); }
    }
  }
  const main = $('#main');
  main.replaceChildren();
  const ctx = makeContext(main);
  current = ctx;
  const { parts, params } = parseHash();
  clearAlerts(3000); // messages of the page left behind
  renderTopbar();
  connectionChanged();

  if (parts[0] === 'login') return renderLogin(ctx);
  if (!state.me) {
    // Not logged in (yet): ask the server who we are.
    try {
      setMe(await api('GET', '/me'));
      await loadCells();
    } catch (e) {
      if (!(e instanceof ApiError) || e.status !== 401) {
        main.append(h('h1', { tabindex: '-1' }, 'The console is not reachable'),
          h('p', null, 'See the message above. ', h('button', { type: 'button', onclick: () => route() }, 'Try again')));
      }
      return;
    }
    if (!ctx.alive) return;
    renderTopbar();
  }

  try {
    if (parts.length === 0) await renderOverview(ctx);
    else if (parts[0] === 'cell' && parts[1]) {
      const cell = parts[1];
      if (!cellNames().includes(cell)) {
        main.append(h('h1', { tabindex: '-1' }, 'No such cell'), h('p', null, `The console knows no cell "${cell}".`));
      } else if (!parts[2]) await renderOverview(ctx, cell);
      else if (parts[2] === 'machine' && parts[3]) await renderMachine(ctx, cell, parts[3]);
      else if (parts[2] === 'programs' && parts[3]) await renderProgram(ctx, cell, parts[3], params);
      else if (parts[2] === 'programs') await renderPrograms(ctx, cell);
      else if (parts[2] === 'plc' && parts[3]) await renderPlc(ctx, cell, parts[3]);
      else if (parts[2] === 'history') await renderHistory(ctx, cell, params);
      else notFound(main);
    } else notFound(main);
  } catch (e) {
    if (!(e instanceof ApiError)) {
      console.error(e);
      alertError(`This page failed: ${e.message || e}`);
    }
  }
  // Keyboard and screen-reader users land on the new page's heading.
  const h1 = $('h1', main);
  if (ctx.alive && h1 && document.activeElement === document.body) h1.focus({ preventScroll: true });
}

function notFound(main) {
  document.title = 'Not found · cellgate';
  main.append(h('h1', { tabindex: '-1' }, 'Page not found'), h('p', null, h('a', { href: '#/' }, 'Back to the overview')));
}

// ---- login ---------------------------------------------------------------------------

function renderLogin(ctx) {
  ctx.title('Log in');
  const user = h('input', { id: 'login-user', name: 'user', autocomplete: 'username', required: true });
  const pass = h('input', { id: 'login-password', name: 'password', type: 'password', autocomplete: 'current-password', required: true });
  const submit = h('button', { id: 'login-submit', type: 'submit' }, 'Log in');
  const form = h('form', { class: 'card login' },
    h('h1', { tabindex: '-1' }, 'Log in to cellgate'),
    field('User', user), field('Password', pass), h('div', { class: 'actions' }, submit));
  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    await act(submit, async () => {
      const me = await api('POST', '/login', { json: { user: user.value, password: pass.value }, noRedirect: true });
      setMe(me);
      await loadCells();
      clearAlerts();
      const to = returnTo && !returnTo.startsWith('#/login') ? returnTo : '#/';
      returnTo = '';
      if (location.hash === to) route();
      else location.hash = to;
    });
  });
  ctx.main.append(form);
  user.focus();
}

// ---- start ---------------------------------------------------------------------------

// The skip link must not change the hash: the router owns it.
$('#skip').addEventListener('click', (e) => {
  e.preventDefault();
  $('#main').focus();
});
window.addEventListener('hashchange', route);
route();

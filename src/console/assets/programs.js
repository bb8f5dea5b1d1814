// The program library: list and upload; one program's text, revisions, states, compare
// and send.
import {
  $, h, append, fill, api, can, enc, cellPath, query, setText, field, select, table, scroller, act, notice,
  bytes, dateTime, revState, who, machinesOf, alertError,
} from './lib.js';

export async function renderPrograms(ctx, cell) {
  ctx.title('Programs');
  const main = ctx.main;
  main.append(h('p', { class: 'crumbs' }, h('a', { href: '#/' }, 'Overview'), ' › ', `cell ${cell}`),
    h('h1', { tabindex: '-1' }, 'Programs'));
  const listBox = h('div');
  const load = async () => {
    const all = (await api('GET', `${cellPath(cell)}/programs`)) || [];
    if (!ctx.alive) return;
    // A file of the folder the library does not take has no program name: listed apart.
    const list = all.filter((p) => p.name);
    const refused = all.filter((p) => !p.name);
    list.sort((a, b) => a.name.localeCompare(b.name));
    const t = table(['Name', 'Size', 'Latest revision', 'State', 'Latest released', 'Stored', 'By'], 'programs');
    t.setAttribute('aria-label', 'Library programs');
    for (const p of list) {
      const l = p.latest || {};
      t.tbody.append(h('tr', { 'data-program': p.name, class: l.removed ? 'removed' : null },
        h('td', null, h('a', { href: `#/cell/${enc(cell)}/programs/${enc(p.name)}` }, p.name)),
        h('td', { class: 'num' }, bytes(p.size)),
        h('td', { class: 'num' }, l.number || '—'),
        h('td', { 'data-field': 'state' }, h('span', { class: `badge rev-${revState(l.state)}` }, revState(l.state)), l.removed ? ' (removed)' : ''),
        h('td', { class: 'num' }, p.latest_released ? String(p.latest_released) : '—'),
        h('td', null, dateTime(p.modified_unix_ms)),
        h('td', null, who(l.by))));
    }
    listBox.replaceChildren(list.length ? scroller(t) : h('p', { class: 'muted' }, 'The library is empty.'));
    if (refused.length) {
      listBox.append(h('p', null, 'Files of the folder not taken:'),
        h('ul', { class: 'refused-files' }, ...refused.map((p) => h('li', null, h('code', null, p.file), ': ', p.note))));
    }
  };

  main.append(h('section', { class: 'card', 'aria-labelledby': 'sec-list' }, h('h2', { id: 'sec-list' }, 'Library'), listBox));
  if (can('program.write')) main.append(uploadForm(cell, load));
  await load().catch(() => listBox.replaceChildren(h('p', { class: 'muted' }, 'The library could not be read.')));
}

function uploadForm(cell, after) {
  const name = h('input', { id: 'upload-name', required: true, pattern: '[A-Za-z0-9._+\\-]{1,128}', autocomplete: 'off', maxlength: '128' });
  const file = h('input', { id: 'upload-file', type: 'file', required: true });
  const comment = h('input', { id: 'upload-comment', maxlength: '1024', autocomplete: 'off' });
  const btn = h('button', { id: 'upload-submit', type: 'submit' }, 'Upload');
  file.addEventListener('change', () => {
    // Suggest the file's name (without extension) when no name was typed.
    if (!name.value && file.files[0]) name.value = file.files[0].name.replace(/\.[^.]*$/, '').replace(/[^A-Za-z0-9._+-]/g, '_').slice(0, 128);
  });
  const form = h('form', { class: 'card stack', 'aria-labelledby': 'sec-upload' }, h('h2', { id: 'sec-upload' }, 'Upload a program'),
    h('div', { class: 'row' }, field('Name', name, 'letters, digits, . _ + -'), field('File', file), field('Comment', comment)),
    h('div', { class: 'actions' }, btn));
  form.addEventListener('submit', (e) => {
    e.preventDefault();
    const f = file.files[0];
    if (!f || !name.value) {
      alertError('Choose a file and give the program a name.');
      return;
    }
    act(btn, async () => {
      const data = await f.arrayBuffer();
      const info = await api('PUT', `${cellPath(cell)}/programs/${enc(name.value)}${query({ comment: comment.value })}`, { body: data });
      notice(`Stored ${info.name}: revision ${info.latest?.number ?? '?'}, ${bytes(info.size)}.`);
      form.reset();
      await after();
    });
  });
  return form;
}

// ---- one program ---------------------------------------------------------------------

const MAX_LINES = 5000;

export async function renderProgram(ctx, cell, name, params) {
  ctx.title(name);
  const main = ctx.main;
  const base = `${cellPath(cell)}/programs/${enc(name)}`;
  main.append(h('p', { class: 'crumbs' }, h('a', { href: '#/' }, 'Overview'), ' › ', h('a', { href: `#/cell/${enc(cell)}/programs` }, 'Programs')),
    h('h1', { tabindex: '-1' }, `Program ${name}`));

  const revBox = h('div');
  const textBox = h('div');
  const textTitle = h('h2', { id: 'sec-text' }, 'Text');
  const diffBox = h('div');
  let revs = [];
  let shown = params.get('rev') || '';

  const showText = async (rev) => {
    shown = rev ? String(rev) : '';
    setText(textTitle, rev ? `Text of revision ${rev}` : 'Text of the latest revision');
    textBox.replaceChildren(h('p', { class: 'muted' }, 'Loading…'));
    try {
      const text = await api('GET', rev ? `${base}/rev/${enc(rev)}` : base, { text: true });
      if (ctx.alive) textBox.replaceChildren(programText(text));
    } catch {
      textBox.replaceChildren(h('p', { class: 'muted' }, 'The text could not be read.'));
    }
  };

  const comment = h('input', { id: 'state-comment', maxlength: '1024', autocomplete: 'off' });
  const setState = (n, state, label, btn) => act(btn, async () => {
    const r = await api('POST', `${base}/release`, { json: { revision: String(n), state, comment: comment.value } });
    notice(`Revision ${r.number} is ${revState(r.state)} now (${label}).`);
    comment.value = '';
    await loadRevs();
  });

  const loadRevs = async () => {
    const r = await api('GET', `${base}/revisions`);
    if (!ctx.alive) return;
    revs = r.revisions || [];
    const t = table(['Rev', 'State', 'Stored', 'By', 'Size', 'SHA-256', 'Comment', 'Actions'], 'revisions');
    t.setAttribute('aria-label', `Revisions of ${name}`);
    for (const x of revs) {
      const n = x.number;
      const b = (action, label, state) => h('button', { type: 'button', class: 'small', 'data-action': action, 'data-rev': String(n),
        onclick: (e) => setState(n, state, label, e.currentTarget) }, label);
      const actions = [h('button', { type: 'button', class: 'small', 'data-action': 'view', 'data-rev': String(n),
        onclick: async () => {
          await showText(n);
          textTitle.scrollIntoView({ block: 'start' });
          $('.code-box', textBox)?.focus({ preventScroll: true });
        } }, 'View')];
      if (can('program.release')) {
        if (x.state === 'REVISION_STATE_DRAFT') actions.push(b('release', 'Release', 'REVISION_STATE_RELEASED'), b('lock', 'Lock', 'REVISION_STATE_LOCKED'));
        else if (x.state === 'REVISION_STATE_RELEASED') actions.push(b('lock', 'Lock', 'REVISION_STATE_LOCKED'), b('unrelease', 'Back to draft', 'REVISION_STATE_DRAFT'));
        else if (x.state === 'REVISION_STATE_LOCKED') actions.push(b('unlock', 'Unlock', 'REVISION_STATE_DRAFT'));
      }
      const stateNote = x.state_unix_ms && x.state !== 'REVISION_STATE_DRAFT'
        ? h('div', { class: 'small-text muted' }, `${dateTime(x.state_unix_ms)} by ${who(x.state_by)}${x.state_comment ? `: ${x.state_comment}` : ''}`) : null;
      t.tbody.append(h('tr', { 'data-rev': String(n) },
        h('td', { class: 'num' }, String(n)),
        h('td', null, h('span', { class: `badge rev-${revState(x.state)}`, 'data-field': 'state' }, revState(x.state)), x.removed ? ' (removed after)' : '', stateNote),
        h('td', { class: 'nowrap' }, dateTime(x.unix_ms)), h('td', null, who(x.by)), h('td', { class: 'num nowrap' }, bytes(x.size)),
        h('td', null, h('code', { title: x.sha256 }, x.sha256.slice(0, 12))),
        h('td', null, x.comment, x.adopted_from ? h('div', { class: 'small-text muted' }, `adopted from ${x.adopted_from} rev ${x.adopted_revision}`) : null),
        h('td', null, h('div', { class: 'actions-cell' }, actions))));
    }
    fill(revBox, r.removed ? h('p', { class: 'warn-text' }, 'This program was removed from the library; its revisions are kept.') : '',
      can('program.release') ? h('div', { class: 'row' }, field('Comment for a change of state', comment)) : null,
      scroller(t));
    fillRevSelects();
  };

  // Compare
  const diffA = h('select', { id: 'diff-a' });
  const diffB = h('select', { id: 'diff-b' });
  const ig = (id, label) => h('label', { class: 'check' }, h('input', { type: 'checkbox', id }), ` ${label}`);
  const showBtn = h('button', { type: 'submit', id: 'diff-show' }, 'Compare');
  const diffForm = h('form', { class: 'stack' },
    h('div', { class: 'row' }, field('A (left)', diffA), field('B (right)', diffB)),
    h('fieldset', null, h('legend', null, 'Ignore'), ig('diff-ignore-sequence', 'sequence numbers (N…)'), ig('diff-ignore-blanks', 'blanks'), ig('diff-ignore-comments', 'comments (…)')),
    h('div', { class: 'actions' }, showBtn));
  const diffResult = h('div', { id: 'diff-result', 'aria-live': 'polite' });
  diffForm.addEventListener('submit', (e) => {
    e.preventDefault();
    const ignore = ['sequence', 'blanks', 'comments'].filter((k) => document.getElementById(`diff-ignore-${k}`).checked).join(',');
    act(showBtn, async () => {
      const d = await api('GET', `${base}/diff${query({ a: diffA.value, b: diffB.value, ignore })}`);
      diffResult.replaceChildren(diffView(d));
    });
  });
  diffBox.append(diffForm, diffResult);

  // Send
  let sendRev = null;
  const sendBox = can('job.submit') ? (() => {
    const machines = machinesOf(cell);
    const m = select('send-machine', machines.map((x) => [x, x]));
    sendRev = h('select', { id: 'send-revision' });
    const prio = h('input', { id: 'send-priority', type: 'number', value: '0', step: '1', inputmode: 'numeric' });
    const btn = h('button', { id: 'send-submit', type: 'submit' }, 'Send');
    const f = h('form', { class: 'stack' }, h('div', { class: 'row' }, field('Machine', m), field('Revision', sendRev), field('Priority', prio)), h('div', { class: 'actions' }, btn));
    f.addEventListener('submit', (e) => {
      e.preventDefault();
      if (!m.value) return;
      act(btn, async () => {
        const a = await api('POST', `${cellPath(cell)}/machines/${enc(m.value)}/submit`, { json: { library: name, revision: sendRev.value, priority: Number(prio.value) || 0, name: '' } });
        notice(`Job ${a.job_id} queued on ${m.value} (${a.program?.library || name} rev ${a.program?.revision ?? '?'}), ${a.queue_position} ahead of it.`);
      });
    });
    return f;
  })() : null;

  const fillRevSelects = () => {
    const opts = (sel, pick) => {
      const keep = sel.value;
      sel.replaceChildren(...revs.map((x) => h('option', { value: String(x.number) }, `${x.number} · ${revState(x.state)} · ${dateTime(x.unix_ms)}`)));
      sel.value = keep && revs.some((x) => String(x.number) === keep) ? keep : pick;
    };
    opts(diffA, revs[1] ? String(revs[1].number) : revs[0] ? String(revs[0].number) : '');
    opts(diffB, revs[0] ? String(revs[0].number) : '');
    if (sendRev) {
      const keep = sendRev.value;
      sendRev.replaceChildren(h('option', { value: '' }, 'latest'), ...revs.map((x) => h('option', { value: String(x.number) }, `${x.number} · ${revState(x.state)}`)));
      sendRev.value = keep;
    }
  };

  const sec = (title, id, ...kids) => h('section', { class: 'card', 'aria-labelledby': id }, typeof title === 'string' ? h('h2', { id }, title) : title, ...kids);
  const textSec = sec(textTitle, 'sec-text', textBox);
  append(main, [sec('Revisions', 'sec-revs', revBox), textSec,
    sec('Compare two revisions', 'sec-diff', diffBox),
    sendBox ? sec('Send to a machine', 'sec-send', sendBox) : null]);
  if (can('program.write')) main.append(removeBox(cell, name, base));

  await loadRevs().catch(() => revBox.replaceChildren(h('p', { class: 'muted' }, 'The revisions could not be read.')));
  await showText(shown);
}

function removeBox(cell, name, base) {
  const btn = h('button', { type: 'button', class: 'danger', 'data-action': 'remove' }, 'Remove from the library…');
  const box = h('section', { class: 'card', 'aria-labelledby': 'sec-remove' }, h('h2', { id: 'sec-remove' }, 'Remove'),
    h('p', { class: 'small-text muted' }, 'The revisions stay readable until retention drops them.'), btn);
  let armed = false;
  btn.addEventListener('click', () => {
    // Two steps instead of a modal dialog: the first click asks, the second removes.
    if (!armed) {
      armed = true;
      btn.textContent = `Yes, remove ${name}`;
      setTimeout(() => { armed = false; btn.textContent = 'Remove from the library…'; }, 6000);
      return;
    }
    act(btn, async () => {
      await api('DELETE', base);
      notice(`${name} removed from the library.`);
      location.hash = `#/cell/${enc(cell)}/programs`;
    });
  });
  return box;
}

// The program's text with line numbers; N words and (comments) marked so blocks read
// easily. Built with text nodes only.
export function programText(text) {
  const lines = text.replace(/\r\n?/g, '\n').replace(/\n$/, '').split('\n');
  const ol = h('ol', { class: 'code' });
  const frag = document.createDocumentFragment();
  const n = Math.min(lines.length, MAX_LINES);
  for (let i = 0; i < n; i++) frag.append(h('li', null, blockSpans(lines[i])));
  ol.append(frag);
  const box = h('div', { class: 'code-box', tabindex: '0', role: 'region', 'aria-label': 'Program text' }, ol);
  if (lines.length > MAX_LINES) {
    const more = h('button', { type: 'button', class: 'small' }, `Show all ${lines.length} lines`);
    more.addEventListener('click', () => {
      const f = document.createDocumentFragment();
      for (let i = MAX_LINES; i < lines.length; i++) f.append(h('li', null, blockSpans(lines[i])));
      ol.append(f);
      more.remove();
    });
    return h('div', null, h('p', { class: 'small-text muted' }, `${lines.length} lines, ${bytes(text.length)}`), box, more);
  }
  return h('div', null, h('p', { class: 'small-text muted' }, `${lines.length} lines, ${bytes(text.length)}`), box);
}

function blockSpans(line) {
  const out = [];
  const re = /(\([^)]*\)?)|(^\s*N\d+)/g;
  let last = 0;
  let m;
  while ((m = re.exec(line))) {
    if (m.index > last) out.push(line.slice(last, m.index));
    out.push(h('span', { class: m[1] ? 'cmt' : 'seq' }, m[0]));
    last = m.index + m[0].length;
    if (!m[0].length) re.lastIndex++;
  }
  if (last < line.length) out.push(line.slice(last));
  if (!out.length) out.push(' ');
  return out;
}

// ProgramDiff side by side: A on the left, B on the right. A changed block is one row, its
// old text beside its new one; removed and added blocks have the other side empty.
export function diffView(d) {
  const rev = (r) => (r ? `revision ${r.number} (${revState(r.state)}, ${dateTime(r.unix_ms)})` : '—');
  const head = h('p', { class: d.same ? 'ok-text' : 'warn-text', 'data-field': 'summary' },
    d.same ? 'The same, block for block' : `${d.blocks_changed} block(s) changed, ${d.blocks_added} added, ${d.blocks_removed} removed`,
    d.ignored?.length ? ` (ignoring ${d.ignored.join(', ')})` : '');
  const t = h('table', { class: 'diff', 'aria-label': `Comparison of ${d.name}` },
    h('thead', null, h('tr', null,
      h('th', { scope: 'col', class: 'ln' }, 'A'), h('th', { scope: 'col' }, `A: ${rev(d.a)}`),
      h('th', { scope: 'col', class: 'ln' }, 'B'), h('th', { scope: 'col' }, `B: ${rev(d.b)}`))));
  const body = h('tbody');
  t.append(body);
  const side = (l, which, op, label) => (l
    ? [h('td', { class: 'ln' }, String(which === 'a' ? l.a_line || '' : l.b_line || '')),
      h('td', { class: which }, h('span', { class: 'sr-only' }, label), h('span', { class: 'mark', 'aria-hidden': 'true' }, op === 'equal' ? '' : which === 'a' ? '− ' : '+ '), l.text)]
    : [h('td', { class: 'ln' }), h('td', { class: `${which} empty` })]);
  for (const hk of d.hunks || []) {
    body.append(h('tr', { class: 'hunk' }, h('td', { colspan: '4' }, `@@ A line ${hk.a_line}, B line ${hk.b_line}`)));
    const lines = hk.lines || [];
    for (let i = 0; i < lines.length;) {
      const l = lines[i];
      if (l.op === 'OP_REMOVED' || l.op === 'OP_ADDED') {
        // A run of removed blocks and the added ones right after it: the changed pairs
        // side by side, the rest on one side only.
        const removed = [];
        const added = [];
        while (i < lines.length && lines[i].op === 'OP_REMOVED') removed.push(lines[i++]);
        while (i < lines.length && lines[i].op === 'OP_ADDED') added.push(lines[i++]);
        const pairs = Math.min(removed.filter((x) => x.changed).length, added.filter((x) => x.changed).length);
        for (let k = 0; k < Math.max(removed.length, added.length); k++) {
          const a = removed[k];
          const b = added[k];
          const paired = k < pairs && a && b;
          const op = paired ? 'changed' : a ? 'removed' : 'added';
          body.append(h('tr', { 'data-op': op, class: paired ? 'changed removed added' : op },
            side(a, 'a', paired ? 'changed' : 'removed', paired ? 'changed from: ' : 'removed: '),
            side(b, 'b', paired ? 'changed' : 'added', paired ? 'changed to: ' : 'added: ')));
        }
        continue;
      }
      body.append(h('tr', { 'data-op': 'equal', class: 'equal' }, side(l, 'a', 'equal', ''), side(l, 'b', 'equal', '')));
      i++;
    }
  }
  return h('div', null, head, d.same && !(d.hunks || []).length ? null : scroller(t));
}

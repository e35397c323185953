// The Chimera web console (issue 17): the page of `sbs FILE.sbs --http`.
// It speaks the network protocol of docs/cli.md over one WebSocket: the
// greeting, `token T` first, then one command per message, one JSON reply
// each ({"cmd": ..., "id": n} -> {"ok", "id", "text", "data" | "error"}),
// plus the pushed streams {"stream": "graph", "data": <show graph>} and
// {"stream": "scope", ...} (scope.js).
// No framework and nothing from the internet: Chart.js comes from Debian.
'use strict';

const SVG = 'http://www.w3.org/2000/svg';
const STATUS_FIELDS = ['rmod', 'rtpu', 'tid', 'S', 'crit', 'state', 'cycle', 'miss', 'refF', 'mezF', 'mezT', 'maxC', 'avgU', 'warn'];

const ui = {
  ws: null, nextId: 1, pending: new Map(), controlling: false, graph: null, selected: null,
  rcItems: [], statusTimer: null, utilChart: null, utilSeries: new Map(), tick: 0,
};

const $ = (id) => document.getElementById(id);
function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'class') e.className = v; else if (k.startsWith('on')) e.addEventListener(k.slice(2), v); else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}
function svg(tag, attrs = {}, text) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
function fmt(v) {
  if (v === null || v === undefined) return '-';
  if (typeof v === 'number') return Number.isInteger(v) ? String(v) : v.toFixed(Math.abs(v) >= 100 ? 1 : 3);
  return String(v);
}
function log(text, isError) {
  const line = el('div', isError ? { class: 'err' } : {}, text);
  $('log').prepend(line);
  while ($('log').childNodes.length > 200) $('log').lastChild.remove();
}

// ------------------------------------------------------------------ the socket

function connect(token) {
  const ws = new WebSocket((location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + '/ws');
  ui.ws = ws;
  ws.onmessage = (ev) => onMessage(JSON.parse(ev.data), token);
  ws.onclose = () => {
    $('link').textContent = 'disconnected';
    $('link').className = 'badge off';
    setControl(false);
    $('control').disabled = true;
    stopStatus();
  };
}

function onMessage(m, token) {
  if (m.stream === 'graph') return drawGraph(m.data);
  if (m.stream === 'scope') return scopeBatch(m.data);
  if (m.cmd === 'hello') {
    if (!m.ok) return loginError(m.error);
    $('subsystem').textContent = m.subsystem;
    ui.ws.send('token ' + token);
    return;
  }
  if (m.cmd === 'token') {
    if (!m.ok) return loginError(m.error);
    $('login').classList.add('hidden');
    $('console').classList.remove('hidden');
    $('link').textContent = 'connected';
    $('link').className = 'badge on';
    $('control').disabled = false;
    start();
    return;
  }
  const done = m.id !== undefined ? ui.pending.get(m.id) : undefined;
  if (done) {
    ui.pending.delete(m.id);
    done(m);
  } else if (!m.ok) {
    log(m.error, true);
    if (/control taken back/.test(m.error)) setControl(false);
  }
}

function loginError(why) {
  $('login').classList.remove('hidden');
  $('console').classList.add('hidden');
  $('login-error').textContent = 'refused: ' + why;
}

/// One command; resolves with the reply object (ok or not).
function request(cmd) {
  return new Promise((resolve) => {
    if (!ui.ws || ui.ws.readyState !== WebSocket.OPEN) return resolve({ ok: false, error: 'not connected' });
    const id = ui.nextId++;
    ui.pending.set(id, resolve);
    ui.ws.send(JSON.stringify({ cmd, id }));
  });
}

/// A command the engineer asked for: the reply goes to the log.
async function command(cmd) {
  const r = await request(cmd);
  log('> ' + cmd);
  if (r.ok) { if (r.text) log(r.text); } else log('error: ' + r.error, true);
  return r;
}

function setControl(on) {
  ui.controlling = on;
  $('control').textContent = on ? 'Release control' : 'Take control';
  $('mode').textContent = on ? 'in control' : 'watching (read-only)';
  document.body.classList.toggle('controlling', on);
}

// ------------------------------------------------------------------ start-up

function start() {
  request('module').then(showLibrary);
  startStatus();
  scopeInit();
}

window.addEventListener('DOMContentLoaded', () => {
  // The token travels in the URL's fragment (#token=...), which the browser
  // never sends to any server; it is dropped from the address bar at once.
  window.addEventListener('hashchange', () => location.reload());  // a new #token=: start again
  const m = /(?:^#|&)token=([^&]*)/.exec(location.hash);
  if (m) {
    history.replaceState(null, '', location.pathname);
    connect(decodeURIComponent(m[1]));
  } else {
    $('login').classList.remove('hidden');
  }
  $('login-form').addEventListener('submit', (e) => {
    e.preventDefault();
    $('login-error').textContent = '';
    connect($('token').value);
  });
  $('control').addEventListener('click', async () => {
    const r = await command(ui.controlling ? 'release' : 'control');
    if (r.ok) setControl(!!(r.data && r.data.control));
  });
  $('cli-form').addEventListener('submit', (e) => {
    e.preventDefault();
    const c = $('cli').value.trim();
    if (c) command(c).then((r) => { if (r.cmd === 'control' && r.ok) setControl(true); if (r.cmd === 'release') setControl(false); });
    $('cli').value = '';
  });
  $('status-rate').addEventListener('change', startStatus);
  for (const b of document.querySelectorAll('#task-actions button[data-sig]'))
    b.addEventListener('click', () => ui.selected && command(b.dataset.sig + ' ' + ui.selected));
  $('add-to-reconfig').addEventListener('click', () => {
    if (!ui.selected) return;
    $('rc-task').value = ui.selected;
  });
  $('rc-add').addEventListener('click', () => {
    if (!$('rc-task').value) return;
    ui.rcItems.push($('rc-sig').value + ' ' + $('rc-task').value);
    checkReconfig();
  });
  $('rc-clear').addEventListener('click', () => { ui.rcItems = []; checkReconfig(); });
  $('rc-apply').addEventListener('click', async () => {
    const r = await command('reconfig ' + ui.rcItems.join(', '));
    if (r.ok) { ui.rcItems = []; checkReconfig(); }
  });
  $('spawn').addEventListener('click', () => {
    const name = $('rmod-title').dataset.rmod;
    if (name) command('spawn ' + name + ' ' + $('spawn-rtpu').value);
  });
});

// ------------------------------------------------------------------ port graph

/// Data-flow layers: tasks fed by nobody first, each task one layer right of
/// its latest producer; a feedback edge (found by depth-first search from the
/// sources) does not count, so the loop through the robot closes backwards.
function layers(tasks, edges) {
  const succ = new Map(tasks.map((t) => [t.rmod, []]));
  const indeg = new Map(tasks.map((t) => [t.rmod, 0]));
  for (const e of edges) if (e.from !== e.to) { succ.get(e.from).push(e.to); indeg.set(e.to, indeg.get(e.to) + 1); }
  const order = [...tasks].sort((a, b) => indeg.get(a.rmod) - indeg.get(b.rmod)).map((t) => t.rmod);
  const state = new Map(), forward = new Map(tasks.map((t) => [t.rmod, []]));
  const visit = (n) => {
    state.set(n, 1);
    for (const s of succ.get(n)) {
      if (state.get(s) === 1) continue;  // back edge: feedback
      forward.get(n).push(s);
      if (!state.get(s)) visit(s);
    }
    state.set(n, 2);
  };
  for (const n of order) if (!state.get(n)) visit(n);
  const layer = new Map(tasks.map((t) => [t.rmod, 0]));
  for (let round = 0; round < tasks.length; ++round)
    for (const [n, ss] of forward) for (const s of ss) if (layer.get(s) < layer.get(n) + 1) layer.set(s, layer.get(n) + 1);
  return layer;
}

function drawGraph(g) {
  ui.graph = g;
  $('illegal').classList.toggle('hidden', !g.illegal_configuration);
  const taskOf = new Map(g.tasks.map((t) => [t.rmod, t]));
  const producers = (v) => g.tasks.filter((t) => t.out.includes(v) || t.out_const.includes(v));
  const edges = [];
  for (const t of g.tasks)
    for (const v of [...t.in, ...t.in_const])
      for (const p of producers(v)) edges.push({ from: p.rmod, to: t.rmod, v, constant: t.in_const.includes(v) });
  const layer = layers(g.tasks, edges.filter((e) => !e.constant));  // constants are set-up, not the control flow
  const bad = new Set(g.problems.filter((p) => p.kind === 'two_producers').map((p) => p.var));

  // Geometry: a column per layer, a lane per RTPU, boxes stacked in a cell.
  const W = 160, COL = 240, LANE_PAD = 26, X0 = 60;
  const ports = (t) => ({ ins: [...t.in_const, ...t.in], outs: [...t.out_const, ...t.out] });
  const heightOf = (t) => { const p = ports(t); return 38 + 14 * Math.max(p.ins.length, p.outs.length, 1); };
  const lanes = [...g.rtpus];
  for (const t of g.tasks) if (!lanes.includes(t.rtpu)) lanes.push(t.rtpu);
  const pos = new Map();
  let y = 8;
  const laneBoxes = [];
  for (const lane of lanes) {
    const cells = new Map();
    for (const t of g.tasks.filter((t) => t.rtpu === lane)) {
      const l = layer.get(t.rmod);
      if (!cells.has(l)) cells.set(l, []);
      cells.get(l).push(t);
    }
    let laneH = 60;
    for (const [l, ts] of cells) {
      let cy = y + LANE_PAD;
      for (const t of ts) { pos.set(t.rmod, { x: X0 + l * COL, y: cy, h: heightOf(t) }); cy += heightOf(t) + 12; }
      laneH = Math.max(laneH, cy - y + LANE_PAD - 12);
    }
    laneBoxes.push({ lane, y, h: laneH });
    y += laneH + 8;
  }
  const maxLayer = Math.max(0, ...layer.values());
  const width = X0 + (maxLayer + 1) * COL;
  y += 70;  // room for the feedback edges that loop under the lanes
  const root = $('graph');
  root.replaceChildren();
  // Drawn at its own size (the panel scrolls): legible whatever the task count.
  root.setAttribute('viewBox', `0 0 ${width} ${y}`);
  root.setAttribute('width', width);
  root.setAttribute('height', y);
  for (const b of laneBoxes) {
    root.append(svg('rect', { class: 'lane', x: 2, y: b.y, width: width - 4, height: b.h, 'data-rtpu': b.lane }));
    root.append(svg('text', { class: 'lane-label', x: 8, y: b.y + 16 }, 'RTPU ' + b.lane + (b.lane === g.master ? ' (master)' : '')));
  }
  const portY = (t, name, side) => {
    const p = pos.get(t.rmod), list = side === 'in' ? ports(t).ins : ports(t).outs;
    return p.y + 40 + 14 * list.indexOf(name);
  };
  // Edges first, under the boxes.
  for (const e of edges) {
    const a = pos.get(e.from), b = pos.get(e.to);
    const sx = a.x + W, sy = portY(taskOf.get(e.from), e.v, 'out'), tx = b.x, ty = portY(taskOf.get(e.to), e.v, 'in');
    const back = tx <= sx;
    const bend = back ? 90 : Math.max(40, (tx - sx) / 2);
    const d = back
      ? `M${sx},${sy} C${sx + bend},${sy} ${sx + bend},${Math.max(sy, ty) + 60} ${(sx + tx) / 2},${Math.max(sy, ty) + 60} S${tx - bend},${ty} ${tx},${ty}`
      : `M${sx},${sy} C${sx + bend},${sy} ${tx - bend},${ty} ${tx},${ty}`;
    const live = taskOf.get(e.from).state === 'ON';
    const path = svg('path', { d, class: 'edge' + (bad.has(e.v) ? ' bad' : e.constant ? ' const' : live ? '' : ' idle'),
      'data-var': e.v, 'data-from': e.from, 'data-to': e.to });
    path.append(svg('title', {}, `${e.v}: ${e.from} → ${e.to}`));
    root.append(path);
  }
  for (const t of g.tasks) {
    const p = pos.get(t.rmod);
    const box = svg('g', { class: `task state-${t.state}` + (ui.selected === t.rmod ? ' selected' : ''),
      'data-rmod': t.rmod, 'data-state': t.state, 'data-rtpu': t.rtpu });
    box.append(svg('rect', { x: p.x, y: p.y, width: W, height: p.h }));
    box.append(svg('text', { x: p.x + 8, y: p.y + 14 }, t.rmod));
    box.append(svg('text', { class: 'module', x: p.x + 8, y: p.y + 27 }, `${t.module} · ${t.state} · ${fmt(t.freq)} Hz`));
    const { ins, outs } = ports(t);
    for (const v of ins) {
      const py = portY(t, v, 'in');
      box.append(svg('circle', { class: 'port', cx: p.x, cy: py, r: 4, 'data-port': v, 'data-dir': 'in' }));
      box.append(svg('text', { class: 'port-label', x: p.x + 7, y: py + 3 }, v));
    }
    for (const v of outs) {
      const py = portY(t, v, 'out');
      box.append(svg('circle', { class: 'port', cx: p.x + W, cy: py, r: 4, 'data-port': v, 'data-dir': 'out' }));
      box.append(svg('text', { class: 'port-label', x: p.x + W - 7, y: py + 3, 'text-anchor': 'end' }, v));
    }
    box.addEventListener('click', () => selectTask(t.rmod));
    root.append(box);
  }
  // §3.3.1 marks, where verification puts them: at the reader's input that
  // nobody produces, at both producers' outputs of a doubly produced variable.
  for (const pr of g.problems) {
    for (const name of pr.tasks) {
      const t = taskOf.get(name);
      if (!t) continue;
      const side = pr.kind === 'no_producer' ? 'in' : 'out';
      const cx = pos.get(name).x + (side === 'in' ? -12 : W + 12), cy = portY(t, pr.var, side);
      const mark = svg('g', { class: 'problem', 'data-kind': pr.kind, 'data-var': pr.var, 'data-task': name });
      mark.append(svg('circle', { class: 'problem-mark', cx, cy, r: 8 }));
      mark.append(svg('text', { class: 'problem-mark-text', x: cx - 2, y: cy + 4 }, '!'));
      mark.append(svg('title', {}, pr.message));
      root.append(mark);
    }
  }
  $('problems').replaceChildren(...g.problems.map((p) => el('li', {}, p.message)));
  // The reconfiguration builder offers the live tasks.
  const current = $('rc-task').value;
  $('rc-task').replaceChildren(...g.tasks.map((t) => el('option', {}, t.rmod)));
  if (taskOf.has(current)) $('rc-task').value = current;
  $('spawn-rtpu').replaceChildren(...g.rtpus.map((r) => el('option', {}, r)));
  scopeRtpus(g.rtpus);
  if (ui.selected && !taskOf.has(ui.selected)) selectTask(null);
  else if (ui.selected) $('task-name').textContent = `${ui.selected} (${taskOf.get(ui.selected).state})`;
  if (ui.rcItems.length) checkReconfig();
  if (ui.statusTimer) refreshStatus();  // the table follows the graph at once, not at the next tick
}

// ------------------------------------------------------------------ one task

async function selectTask(rmod) {
  ui.selected = rmod;
  for (const b of document.querySelectorAll('#graph .task')) b.classList.toggle('selected', b.dataset.rmod === rmod);
  $('task-actions').classList.toggle('hidden', !rmod);
  $('task-name').textContent = rmod || '(click a box)';
  if (!rmod) return;
  const [local, vars] = await Promise.all([request('set ' + rmod), request('display ' + rmod)]);
  const keys = $('local-keys');
  keys.replaceChildren(el('tr', {}, el('th', {}, 'key'), el('th', {}, 'value'), el('th', {}, 'range'), el('th', {}, '')));
  if (local.ok) {
    const decl = new Map((local.data.keys || []).map((k) => [k.name, k]));
    for (const [key, value] of Object.entries(local.data.local || {})) {
      const d = decl.get(key) || {};
      const input = el('input', { class: 'value', value, 'data-key': key });
      const range = d.type ? `${d.type} [${d.min ?? '-inf'}, ${d.max ?? 'inf'}] ${d.live ? 'live' : 'spawn-only'}` : '';
      keys.append(el('tr', { title: d.help || '' }, el('td', {}, key), el('td', {}, input), el('td', {}, range),
        el('td', {}, el('button', { onclick: () => command(`set ${rmod} ${key} ${input.value}`).then(() => selectTask(rmod)) }, 'set'))));
    }
  }
  fillVars($('task-vars'), vars);
}

/// A table of variables with their values and a write field each (setvar,
/// with the command line's checks: range, type, a producing task).
function fillVars(table, reply) {
  table.replaceChildren(el('tr', {}, el('th', {}, 'dir'), el('th', {}, 'variable'), el('th', {}, 'type'),
    el('th', {}, 'values'), el('th', {}, 'write')));
  if (!reply.ok) return;
  for (const v of reply.data.vars) {
    const input = el('input', { class: 'value', placeholder: 'v1 v2 …', 'data-var': v.name });
    const shown = v.values ? v.values.slice(0, 12).map(fmt).join(' ') + (v.values.length > 12 ? ` … (${v.values.length})` : '') : '(struct)';
    table.append(el('tr', { 'data-var': v.name }, el('td', {}, v.dir || ''), el('td', { title: v.desc || '' }, v.name),
      el('td', {}, `${v.type}[${v.nelem}] ${v.units || ''}`), el('td', { class: 'values' }, shown),
      el('td', {}, input, el('button', { onclick: () => command(`setvar ${v.name} ${input.value}`) }, 'write'))));
  }
}

// ------------------------------------------------------------------ reconfig

/// Every change of the list asks the master whether verification would
/// accept it (reconfig --check sends nothing): a refusal shows, with its
/// reason, before anything changes.
async function checkReconfig() {
  const items = ui.rcItems;
  $('rc-items').replaceChildren(...items.map((it, i) =>
    el('li', {}, it + ' ', el('button', { onclick: () => { ui.rcItems.splice(i, 1); checkReconfig(); } }, '×'))));
  const verdict = $('rc-verdict');
  if (!items.length) {
    verdict.textContent = 'an empty list';
    verdict.className = 'muted';
    $('rc-apply').disabled = true;
    return;
  }
  const r = await request('reconfig --check ' + items.join(', '));
  if (items !== ui.rcItems) return;  // the list changed meanwhile
  verdict.textContent = r.ok ? r.text.replace(/^reconfig --check: /, 'verifies: ') : r.error;
  verdict.className = r.ok ? 'ok' : 'refused';
  $('rc-apply').disabled = !r.ok;
}

// ------------------------------------------------------------------ library

function showLibrary(r) {
  if (!r.ok) return;
  $('library').replaceChildren(...r.data.rmods.map((m) =>
    el('li', { 'data-rmod': m.name, onclick: () => showRmod(m.name) }, el('b', {}, m.name), ' ', el('span', { class: 'muted' }, `${m.module}: ${m.desc || ''}`))));
}

async function showRmod(name) {
  const r = await request('module ' + name);
  if (!r.ok) return log('error: ' + r.error, true);
  const f = r.data.rmods[0];
  $('rmod-detail').classList.remove('hidden');
  $('rmod-title').textContent = `${f.name} (module ${f.module}, ${f.tasktype}, ${fmt(f.freq)} Hz)`;
  $('rmod-title').dataset.rmod = f.name;
  $('rmod-desc').textContent = f.desc || '';
  const rows = [el('tr', {}, el('th', {}, 'port'), el('th', {}, 'SVAR'), el('th', {}, 'type'))];
  for (const [dir, list] of Object.entries(f.ports))
    for (const p of list) rows.push(el('tr', {}, el('td', {}, `${dir} ${p.port}`), el('td', {}, p.svar), el('td', {}, `${p.type || ''} ${p.units || ''}`)));
  for (const [k, v] of Object.entries(f.local)) rows.push(el('tr', {}, el('td', {}, 'LOCAL ' + k), el('td', {}, v), el('td', {}, '')));
  $('rmod-ports').replaceChildren(...rows);
}

// ------------------------------------------------------------------ status

function stopStatus() { if (ui.statusTimer) clearInterval(ui.statusTimer); ui.statusTimer = null; }
function startStatus() {
  stopStatus();
  const ms = Number($('status-rate').value);
  if (ms > 0) ui.statusTimer = setInterval(refreshStatus, ms);
  refreshStatus();
}

async function refreshStatus() {
  const [st, rt, vars] = await Promise.all([request('status all'), ui.tick++ % 5 === 0 ? request('show rtpu') : null,
    request('display all')]);
  if (st.ok) {
    const t = $('status');
    t.replaceChildren(el('tr', {}, ...STATUS_FIELDS.map((f) => el('th', {}, f + (['mezT', 'maxC'].includes(f) ? '[us]' : f === 'avgU' ? '[%]' : '')))));
    for (const row of st.data.tasks) {
      const tr = el('tr', { class: 'state-' + row.state, 'data-rmod': row.rmod },
        ...STATUS_FIELDS.map((f) => el('td', { class: typeof row[f] === 'number' ? 'num' : '' }, fmt(row[f]))));
      t.append(tr);
      if (row.warning) t.append(el('tr', {}, el('td', { colspan: STATUS_FIELDS.length }, 'WARNING> ' + row.warning)));
      if (row.error) t.append(el('tr', {}, el('td', { colspan: STATUS_FIELDS.length, class: 'error' }, 'ERROR> ' + row.error)));
    }
    measuredUtilisation(st.data.tasks);
  }
  if (rt && rt.ok) ui.rtpus = rt.data.rtpus;
  if (ui.rtpus) {
    const used = ui.measured || new Map();
    $('rtpus').replaceChildren(el('tr', {}, ...['RTPU', 'CPU', 'scheduler', 'ranking', 'U planned', 'U measured', 'tasks'].map((h) => el('th', {}, h))),
      ...ui.rtpus.map((r) => el('tr', { 'data-rtpu': r.name }, el('td', {}, r.name), el('td', {}, r.cpu), el('td', {}, r.scheduler),
        el('td', {}, r.ranking), el('td', { class: 'num' }, (100 * r.planned_utilisation).toFixed(1) + ' %'),
        el('td', { class: 'num' }, (used.get(r.name) || 0).toFixed(2) + ' %'), el('td', {}, r.tasks.join(' ')))));
  }
  if (vars.ok) fillVars($('vars'), vars);
}

/// Measured RTPU utilisation: the sum of its tasks' average CPU utilisation
/// per cycle (avgU, %) in the window, plotted with Chart.js when present.
function measuredUtilisation(tasks) {
  const used = new Map();
  for (const t of tasks) if (t.state === 'ON' && typeof t.avgU === 'number') used.set(t.rtpu, (used.get(t.rtpu) || 0) + t.avgU);
  ui.measured = used;
  if (typeof Chart === 'undefined') return;
  if (!ui.utilChart) {
    ui.utilChart = new Chart($('util-chart'), {
      type: 'line', data: { labels: [], datasets: [] },
      options: { animation: false, maintainAspectRatio: false, scales: { y: { beginAtZero: true, title: { display: true, text: 'RTPU utilisation %' } } } },
    });
  }
  const c = ui.utilChart;
  c.data.labels.push(new Date().toLocaleTimeString());
  for (const [rtpu, u] of used) {
    let ds = c.data.datasets.find((d) => d.label === rtpu);
    if (!ds) {
      const colour = ['#3949ab', '#e65100', '#2e7d32', '#ad1457', '#00838f'][c.data.datasets.length % 5];
      ds = { label: rtpu, data: Array(c.data.labels.length - 1).fill(null), pointRadius: 0, borderColor: colour, backgroundColor: colour };
      c.data.datasets.push(ds);
    }
  }
  for (const ds of c.data.datasets) ds.data.push(used.get(ds.label) ?? 0);
  if (c.data.labels.length > 120) { c.data.labels.shift(); for (const ds of c.data.datasets) ds.data.shift(); }
  c.update();
}

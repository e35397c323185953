// The scope of the web console (issue 17.5): chosen elements of state
// variables, sampled on the real-time side by the page's own `sample` task
// and streamed over the page's WebSocket as numbered batches
// ({"stream": "scope"}, tools/sbs/scope_stream.hpp).
//
// - Every sample is kept at full rate (the last few windows); the display
//   is redrawn at FRAME_HZ frames per second, each trace decimated to a min
//   and a max per pixel column. The CSV export takes the captured window's
//   samples at full rate, formatted as `record` writes them.
// - The page acknowledges the batches it has taken (`scope ack N`); a page
//   too busy to do so stops the server reading, the ring laps it, and the
//   samples lost are counted and shown.
// - Trigger: auto / normal / single on a level crossing (rising or falling)
//   of one trace, one division of pre-trigger; pause; two cursors.
'use strict';

const FRAME_HZ = 25;
const DIVISIONS = 10, PRE_TRIGGER_DIVS = 1;
const TIME_PER_DIV = [1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3, 0.1, 0.2, 0.5, 1, 2, 5, 10];
const TRACE_COLOURS = ['#e65100', '#1565c0', '#2e7d32', '#ad1457', '#6a1b9a', '#00838f', '#5d4037', '#9e9d24'];
const MAX_TRACES = 8;

const sc = {
  traces: [],          // ["Q_MEZ[0]", ...] as picked
  run: null,           // {rmod, channels, rate} of the running scope
  buf: null,           // {n, tns, t, v: [[...] per channel]} at full rate
  lastBatch: 0, acked: 0, lost: 0, received: 0,
  shown: null,         // {t0, t1, tRef, triggered, data: {n, tns, t, v}}
  searchFrom: 0,       // buffer index where the trigger search goes on
  lastTrigger: -Infinity,
  paused: false, stopped: false,
  cursors: [null, null], nextCursor: 0,
  chart: null, timer: null, frames: [],
};

// ------------------------------------------------------------------ numbers

/// The text std::to_chars gives a double (the shortest that reads back the
/// same, fixed or scientific whichever is shorter, fixed on a tie), so the
/// page's CSV reads as `record`'s does.
function cppNumber(v) {
  if (v === null || Number.isNaN(v)) return 'nan';
  if (!Number.isFinite(v)) return v > 0 ? 'inf' : '-inf';
  if (v === 0) return Object.is(v, -0) ? '-0' : '0';
  const sign = v < 0 ? '-' : '';
  const [mant, e] = Math.abs(v).toExponential().split('e');
  const digits = mant.replace('.', ''), exp = Number(e);
  let fixed;
  if (exp >= digits.length - 1) fixed = digits + '0'.repeat(exp - digits.length + 1);
  else if (exp >= 0) fixed = digits.slice(0, exp + 1) + '.' + digits.slice(exp + 1);
  else fixed = '0.' + '0'.repeat(-exp - 1) + digits;
  const sci = digits[0] + (digits.length > 1 ? '.' + digits.slice(1) : '') + 'e' + (exp < 0 ? '-' : '+') +
    String(Math.abs(exp)).padStart(2, '0');
  return sign + (fixed.length <= sci.length ? fixed : sci);
}

function timeText(s) {
  const a = Math.abs(s);
  if (a < 1e-12) return '0 s';  // a tick at the trigger, off by a rounding
  if (a < 1e-3) return (s * 1e6).toPrecision(4) + ' µs';
  if (a < 1) return (s * 1e3).toPrecision(4) + ' ms';
  return s.toPrecision(4) + ' s';
}

// ------------------------------------------------------------------ picking traces

async function scopeInit() {
  const r = await request('display all');
  if (!r.ok) return;
  const numeric = r.data.vars.filter((v) => Array.isArray(v.values));
  $('sc-var').replaceChildren(...numeric.map((v) => el('option', { value: v.name, 'data-nelem': v.nelem }, v.name)));
  fillElements();
}

function fillElements() {
  const opt = $('sc-var').selectedOptions[0];
  const n = opt ? Number(opt.dataset.nelem) : 0;
  $('sc-elem').replaceChildren(...Array.from({ length: n }, (_, i) => el('option', { value: i }, String(i))));
}

function addTrace() {
  const name = `${$('sc-var').value}[${$('sc-elem').value}]`;
  if (!$('sc-var').value || sc.traces.includes(name) || sc.traces.length >= MAX_TRACES) return;
  sc.traces.push(name);
  showTraces();
}

function showTraces() {
  $('sc-traces').replaceChildren(...sc.traces.map((name, i) => el('li', { 'data-trace': name },
    el('span', { class: 'swatch', style: `background:${TRACE_COLOURS[i]}` }), name, ' ',
    el('button', { onclick: () => { sc.traces.splice(i, 1); showTraces(); } }, '×'))));
  const trig = $('sc-trig-trace'), was = trig.value;
  trig.replaceChildren(...sc.traces.map((name, i) => el('option', { value: i }, name)));
  if (was && Number(was) < sc.traces.length) trig.value = was;
  $('sc-run').disabled = sc.traces.length === 0;
}

/// Where the sampler task runs: under RM it outranks the slower tasks of its
/// RTPU, so an RTPU of its own keeps the controllers' timing as it was.
function scopeRtpus(rtpus) {
  const sel = $('sc-rtpu'), was = sel.value;
  sel.replaceChildren(el('option', { value: '' }, "the master's"), ...rtpus.map((r) => el('option', { value: r }, r)));
  if (rtpus.includes(was)) sel.value = was;
}

// ------------------------------------------------------------------ running

async function runScope() {
  if (!sc.traces.length) return;
  const rate = $('sc-rate').value.trim();
  const rtpu = $('sc-rtpu').value;
  const r = await command('scope start ' + sc.traces.join(' ') + (rate ? ' --rate ' + rate : '') + (rtpu ? ' --rtpu ' + rtpu : ''));
  if (!r.ok) return;
  sc.run = { rmod: r.data.rmod, channels: r.data.channels, rate: r.data.rate };
  sc.buf = { n: [], tns: [], t: [], v: r.data.channels.map(() => []) };
  Object.assign(sc, { lastBatch: 0, acked: 0, lost: 0, received: 0, shown: null, searchFrom: 0, lastTrigger: -Infinity,
    stopped: false, cursors: [null, null], nextCursor: 0 });
  makeChart();
  if (!sc.timer) sc.timer = setInterval(frame, 1000 / FRAME_HZ);
  setState();
}

async function stopScope() {
  if (!sc.run) return;
  await command('scope stop');
  sc.run = null;
  setState();
}

/// A batch from the server: appended at full rate; acknowledged at the next frame.
function scopeBatch(d) {
  if (!sc.run || d.rmod !== sc.run.rmod) return;  // a batch of the scope just replaced
  const b = sc.buf;
  for (let k = 0; k < d.n.length; ++k) {
    b.n.push(d.n[k]);
    b.tns.push(d.t[k]);
    b.t.push(d.t[k] / 1e9);
    for (let i = 0; i < b.v.length; ++i) b.v[i].push(d.values[i][k]);
  }
  sc.received += d.n.length;
  sc.lost = d.lost_total;
  sc.lastBatch = d.batch;
  if (d.closed) { log(`scope: ${sc.run.rmod} stopped`); sc.run = null; setState(); }
}

/// Keeps the samples of the last three windows (and at least 10000).
function trimBuffer(windowSeconds) {
  const b = sc.buf, keep = Math.max(10000, Math.ceil(3 * windowSeconds * (sc.run ? sc.run.rate : 1000)));
  const extra = b.n.length - keep;
  if (extra < keep / 2) return;  // trimmed in chunks: amortised
  for (const a of [b.n, b.tns, b.t, ...b.v]) a.splice(0, extra);
  sc.searchFrom = Math.max(0, sc.searchFrom - extra);
}

// ------------------------------------------------------------------ trigger

function windowSeconds() { return DIVISIONS * Number($('sc-tdiv').value); }

/// Index of the first sample at or after time t (binary search).
function indexAt(t) {
  const a = sc.buf.t;
  let lo = 0, hi = a.length;
  while (lo < hi) { const mid = (lo + hi) >> 1; if (a[mid] < t) lo = mid + 1; else hi = mid; }
  return lo;
}

/// The newest crossing of the level on the trigger trace after `from` whose
/// whole window (after the pre-trigger) has arrived, or -1; `searched`: the
/// last sample looked at (the next search starts there).
function findTrigger(from) {
  const b = sc.buf, i = Number($('sc-trig-trace').value || 0), v = b.v[i];
  if (!v || !b.t.length) return { k: -1, searched: from };
  const level = Number($('sc-level').value), rising = $('sc-slope').value === 'rising';
  const last = Math.min(indexAt(b.t[b.t.length - 1] - (windowSeconds() - preTrigger()) + 1e-12) - 1, b.t.length - 1);
  for (let k = last; k > Math.max(from, 0); --k) {
    const a = v[k - 1], c = v[k];
    if (a === null || c === null) continue;
    if (rising ? a < level && c >= level : a > level && c <= level) return { k, searched: last };
  }
  return { k: -1, searched: Math.max(from, last) };
}

function preTrigger() { return PRE_TRIGGER_DIVS * Number($('sc-tdiv').value); }

/// The samples of [t0, t1] at full rate, copied (a held window outlives trimming).
function extract(t0, t1) {
  const b = sc.buf, i0 = indexAt(t0), i1 = indexAt(t1 + 1e-12);
  return { n: b.n.slice(i0, i1), tns: b.tns.slice(i0, i1), t: b.t.slice(i0, i1), v: b.v.map((c) => c.slice(i0, i1)) };
}

/// What this frame shows: a new triggered window, the held one, or (auto,
/// no trigger for a window's time) the newest window rolling.
function nextWindow() {
  const b = sc.buf, W = windowSeconds(), mode = $('sc-mode').value;
  if (!b.t.length) return sc.shown;
  const { k, searched } = findTrigger(sc.searchFrom);
  if (k < 0) sc.searchFrom = searched;  // each sample is searched once
  const tEnd = b.t[b.t.length - 1];
  if (k >= 0) {
    const tRef = b.t[k];
    sc.searchFrom = indexAt(tRef + W - preTrigger());  // hold-off: the next window starts after this one
    sc.lastTrigger = tEnd;
    if (mode === 'single') sc.stopped = true;
    return { t0: tRef - preTrigger(), t1: tRef - preTrigger() + W, tRef, triggered: true, data: extract(tRef - preTrigger(), tRef - preTrigger() + W) };
  }
  if (mode === 'auto' && tEnd - sc.lastTrigger > W) {
    const t0 = Math.max(0, tEnd - W);
    return { t0, t1: t0 + W, tRef: t0, triggered: false, data: extract(t0, t0 + W) };
  }
  return sc.shown;
}

// ------------------------------------------------------------------ the frame

function frame() {
  const now = performance.now();
  sc.frames.push(now);
  while (sc.frames.length && now - sc.frames[0] > 1000) sc.frames.shift();
  if (!sc.buf) return;
  if (sc.run && sc.lastBatch > sc.acked) { ws_send('scope ack ' + sc.lastBatch); sc.acked = sc.lastBatch; }
  if (!sc.paused && !sc.stopped) {
    const shown = nextWindow();
    if (shown !== sc.shown) { sc.shown = shown; draw(); }
  }
  trimBuffer(windowSeconds());
  stats();
}

function ws_send(text) { if (ui.ws && ui.ws.readyState === WebSocket.OPEN) ui.ws.send(text); }

/// Min and max of each pixel column, in the order they came (so the line
/// draws the envelope); the raw samples when there are fewer than two per column.
function decimate(t, v, t0, W, columns, tRef) {
  if (t.length <= 2 * columns) return t.map((x, k) => ({ x: x - tRef, y: v[k] }));
  const out = [];
  let col = -1, lo = 0, hi = 0;
  const flush = () => { if (col >= 0) { const [a, b] = lo < hi ? [lo, hi] : [hi, lo]; out.push({ x: t[a] - tRef, y: v[a] }); if (b !== a) out.push({ x: t[b] - tRef, y: v[b] }); } };
  for (let k = 0; k < t.length; ++k) {
    if (v[k] === null) continue;
    const c = Math.floor((t[k] - t0) / W * columns);
    if (c !== col) { flush(); col = c; lo = hi = k; continue; }
    if (v[k] < v[lo]) lo = k;
    if (v[k] > v[hi]) hi = k;
  }
  flush();
  return out;
}

function draw() {
  const s = sc.shown, c = sc.chart;
  if (!s || !c) return;
  const W = s.t1 - s.t0, columns = Math.max(50, Math.round(c.chartArea ? c.chartArea.width : 800));
  c.data.datasets.forEach((ds, i) => { ds.data = decimate(s.data.t, s.data.v[i], s.t0, W, columns, s.tRef); });
  c.options.scales.x.min = s.t0 - s.tRef;
  c.options.scales.x.max = s.t1 - s.tRef;
  c.options.scales.x.ticks.stepSize = Number($('sc-tdiv').value);
  c.options.scales.x.title.text = s.triggered ? 'time from trigger [s]' : 'time from the window\'s start (untriggered) [s]';
  c.update('none');
  $('scope-chart').dataset.points = c.data.datasets.map((d) => d.data.length).join(' ');
  $('scope-chart').dataset.samples = s.data.n.length;
  $('scope-chart').dataset.triggered = s.triggered ? 'yes' : 'no';
  readout();
  setState();
}

function stats() {
  const rate = sc.run ? `${cppNumber(sc.run.rate)} Hz` : 'stopped';
  $('sc-received').textContent = sc.received;
  $('sc-lost').textContent = sc.lost;
  $('sc-lost').classList.toggle('error', sc.lost > 0);
  $('sc-fps').textContent = `${sc.frames.length} fps (target ${FRAME_HZ})`;
  $('sc-rate-shown').textContent = rate;
}

function setState() {
  const state = !sc.run && !sc.shown ? 'off' : sc.paused ? 'paused' : sc.stopped ? 'single: captured (arm again)'
    : !sc.run ? 'stopped' : sc.shown && sc.shown.triggered ? 'triggered'
    : sc.shown && $('sc-mode').value === 'auto' ? 'auto: no trigger, rolling' : 'armed, waiting for a trigger';
  $('sc-state').textContent = state;
  $('sc-pause').textContent = sc.paused ? 'resume' : 'pause';
}

// ------------------------------------------------------------------ chart, cursors

function makeChart() {
  if (typeof Chart === 'undefined') return;
  if (sc.chart) sc.chart.destroy();
  const overlay = { id: 'scopeOverlay', afterDraw: drawOverlay };
  sc.chart = new Chart($('scope-chart'), {
    type: 'line',
    data: { datasets: sc.run.channels.map((name, i) => ({ label: name, data: [], borderColor: TRACE_COLOURS[i], backgroundColor: TRACE_COLOURS[i], borderWidth: 1.2, pointRadius: 0 })) },
    options: {
      animation: false, parsing: false, normalized: true, maintainAspectRatio: false, spanGaps: false,
      scales: { x: { type: 'linear', title: { display: true, text: 'time from trigger [s]' }, ticks: { maxTicksLimit: 11, callback: (v) => timeText(v) } },
        y: { title: { display: true, text: 'value' } } },
      plugins: { legend: { position: 'top' }, tooltip: { enabled: false } },
    },
    plugins: [overlay],
  });
}

/// The trigger level (dashed) and the two cursors, over the traces.
function drawOverlay(chart) {
  const { ctx, chartArea: a, scales: { x, y } } = chart;
  ctx.save();
  const level = Number($('sc-level').value);
  if (level >= y.min && level <= y.max) {
    ctx.strokeStyle = '#888'; ctx.setLineDash([4, 4]);
    ctx.beginPath(); ctx.moveTo(a.left, y.getPixelForValue(level)); ctx.lineTo(a.right, y.getPixelForValue(level)); ctx.stroke();
  }
  ctx.setLineDash([]);
  sc.cursors.forEach((c, i) => {
    if (c === null || !sc.shown) return;
    const px = x.getPixelForValue(c - sc.shown.tRef);
    ctx.strokeStyle = i ? '#c62828' : '#283593';
    ctx.beginPath(); ctx.moveTo(px, a.top); ctx.lineTo(px, a.bottom); ctx.stroke();
    ctx.fillStyle = ctx.strokeStyle; ctx.fillText(i ? 'B' : 'A', px + 3, a.top + 10);
  });
  ctx.restore();
}

// A DOM listener, not Chart.js's onClick, which is throttled to one event per animation frame.
function placeCursor(ev) {
  if (!sc.shown || !sc.chart) return;
  const t = sc.chart.scales.x.getValueForPixel(ev.offsetX) + sc.shown.tRef;
  const which = ev.shiftKey ? 1 : sc.nextCursor;
  setCursor(which, t);
  sc.nextCursor = which ? 0 : 1;
}

/// Cursor 0 (A) or 1 (B) at time t (seconds, the stream's time); null removes it.
function setCursor(which, t) {
  sc.cursors[which] = t;
  readout();
  if (sc.chart) sc.chart.update('none');
}

/// The captured sample nearest to time t.
function nearest(t) {
  const d = sc.shown.data.t;
  if (!d.length) return -1;
  let lo = 0, hi = d.length - 1;
  while (lo < hi) { const mid = (lo + hi) >> 1; if (d[mid] < t) lo = mid + 1; else hi = mid; }
  return lo > 0 && t - d[lo - 1] < d[lo] - t ? lo - 1 : lo;
}

function readout() {
  const [a, b] = sc.cursors, table = $('sc-readout');
  if (!sc.shown || (a === null && b === null)) return table.replaceChildren();
  const ka = a === null ? -1 : nearest(a), kb = b === null ? -1 : nearest(b);
  const d = sc.shown.data, at = (k) => (k < 0 ? null : d.t[k]);
  const rows = [el('tr', {}, el('th', {}, ''), el('th', {}, 'A'), el('th', {}, 'B'), el('th', {}, 'Δ (B − A)'))];
  const dt = ka >= 0 && kb >= 0 ? at(kb) - at(ka) : null;
  rows.push(el('tr', { 'data-row': 't' }, el('td', {}, 't'), el('td', { class: 'num' }, ka < 0 ? '-' : timeText(at(ka) - sc.shown.tRef)),
    el('td', { class: 'num' }, kb < 0 ? '-' : timeText(at(kb) - sc.shown.tRef)),
    el('td', { class: 'num', 'data-dt': dt ?? '' }, dt === null ? '-' : `${timeText(dt)}${dt ? ` (${cppNumber(1 / Math.abs(dt)).slice(0, 8)} Hz)` : ''}`)));
  (sc.run ? sc.run.channels : sc.traces).forEach((name, i) => {
    const va = ka < 0 ? null : d.v[i][ka], vb = kb < 0 ? null : d.v[i][kb];
    const dv = va !== null && vb !== null ? vb - va : null;
    rows.push(el('tr', { 'data-row': name }, el('td', {}, name), el('td', { class: 'num' }, fmt(va)), el('td', { class: 'num' }, fmt(vb)),
      el('td', { class: 'num', 'data-dv': dv ?? '' }, fmt(dv))));
  });
  table.replaceChildren(...rows);
}

// ------------------------------------------------------------------ export

/// The captured window as CSV, every sample at full rate, in `record`'s
/// format: `t,CHANNEL...`, t in seconds from the window's first sample.
function scopeCsv() {
  const s = sc.shown;
  if (!s || !s.data.n.length) return null;
  const d = s.data, names = sc.chart ? sc.chart.data.datasets.map((x) => x.label) : sc.traces;
  const lines = ['t,' + names.join(',')];
  for (let k = 0; k < d.n.length; ++k)
    lines.push([cppNumber((d.tns[k] - d.tns[0]) / 1e9), ...d.v.map((c) => cppNumber(c[k]))].join(','));
  return lines.join('\n') + '\n';
}

function exportCsv() {
  const text = scopeCsv();
  if (text === null) return log('scope: nothing captured to export', true);
  const a = el('a', { href: URL.createObjectURL(new Blob([text], { type: 'text/csv' })), download: 'scope.csv' });
  document.body.append(a);
  a.click();
  a.remove();
  log(`scope: exported ${sc.shown.data.n.length} samples to scope.csv`);
}

window.addEventListener('DOMContentLoaded', () => {
  $('sc-tdiv').replaceChildren(...TIME_PER_DIV.map((s) => el('option', { value: s }, timeText(s) + '/div')));
  $('sc-tdiv').value = '0.1';
  $('sc-var').addEventListener('change', fillElements);
  $('sc-add').addEventListener('click', addTrace);
  $('sc-run').addEventListener('click', runScope);
  $('sc-stop').addEventListener('click', stopScope);
  $('sc-pause').addEventListener('click', () => { sc.paused = !sc.paused; setState(); });
  $('sc-arm').addEventListener('click', () => { sc.stopped = false; sc.searchFrom = sc.buf ? sc.buf.t.length : 0; setState(); });
  $('sc-export').addEventListener('click', exportCsv);
  $('scope-chart').addEventListener('click', placeCursor);
  $('sc-cursor-clear').addEventListener('click', () => { setCursor(0, null); setCursor(1, null); sc.nextCursor = 0; });
  for (const id of ['sc-tdiv', 'sc-mode', 'sc-trig-trace', 'sc-slope', 'sc-level'])
    $(id).addEventListener('change', () => { sc.searchFrom = 0; sc.lastTrigger = -Infinity; sc.stopped = false; setState(); });
});

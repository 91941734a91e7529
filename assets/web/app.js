// The rig console's page: talks to `rigctl web` only. Requests go to /api/request with the
// token in the X-Rigd-Token header; events and the live view come over /ws.
'use strict';

const token = new URLSearchParams(location.search).get('token') || '';
const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
const num = (x, d) => (x === null || x === undefined || !isFinite(x)) ? '–' : Number(x).toFixed(d);

// What the page knows; `window.rig` so tests and benchmarks can read it.
const rig = window.rig = {
  daemon: 'connecting', state: null, status: null, position: null, moving: false,
  frames: 0, paintedSequence: null, latencies: [], paints: [], paused: false,
  zoom: '', lastFrame: null, history: {}, best: {},
};

async function api(req) {
  const r = await fetch('/api/request', {
    method: 'POST',
    headers: { 'Content-Type': 'application/json', 'X-Rigd-Token': token },
    body: JSON.stringify(req),
  });
  return r.json();
}

async function getJson(path) {
  const r = await fetch(path, { headers: { 'X-Rigd-Token': token } });
  return r.json();
}

const withToken = (path) => `${path}?token=${encodeURIComponent(token)}`;

// ---- the WebSocket: events and the live view ----
let ws = null;

function connect() {
  ws = new WebSocket(withToken(`ws://${location.host}/ws`));
  ws.onmessage = (m) => onLine(JSON.parse(m.data));
  ws.onclose = () => {
    setDaemon('down', 'connection to the gateway lost: reconnecting');
    setTimeout(connect, 500);
  };
}

function onLine(l) {
  if (l.type === 'gateway') {
    setDaemon(l.daemon === 'up' ? 'up' : 'down', l.error || '');
    if (l.daemon === 'up') { sendView(); refreshAll(); }
    return;
  }
  if (l.type === 'reply' && l.ok === false) {
    $('view-stats').textContent = `preview: ${l.error.message}`;
    return;
  }
  if (l.type !== 'event') return;
  if (l.event === 'preview') { if (rig.paused) ack(); else showFrame(l); return; }
  onJobEvent(l);
}

function setDaemon(state, why) {
  rig.daemon = state;
  const c = $('conn');
  c.className = `badge ${state}`;
  c.textContent = state === 'up' ? 'daemon: connected' : `daemon: ${state}`;
  c.title = why || '';
  if (state !== 'up') { $('rig-reason').textContent = why || ''; }
  updateControls();
}

// ---- live view ----
function sendView() {
  if (!ws || ws.readyState !== WebSocket.OPEN) return;
  if (rig.paused) { ws.send(JSON.stringify({ preview: null })); return; }
  const f = rig.lastFrame;
  const t = f && f.targets.find((t, i) => targetName(t, i) === rig.zoom);
  if (!t) { ws.send(JSON.stringify({ preview: { max_fps: 15, scale: 0.5 } })); return; }
  const r = Math.ceil(t.outer_radius_px * 2.5);
  const x = Math.max(0, Math.round(t.centre_px[0] - r));
  const y = Math.max(0, Math.round(t.centre_px[1] - r));
  const crop = [x, y, Math.min(2 * r, f.frame_size[0] - x), Math.min(2 * r, f.frame_size[1] - y)];
  ws.send(JSON.stringify({ preview: { max_fps: 15, scale: 1, crop } }));
}

const targetName = (t, i) => t.name || `#${i + 1}`;

// Tell the gateway the frame is on screen: it sends the next one only then.
const ack = () => { if (ws && ws.readyState === WebSocket.OPEN) ws.send('{"painted": true}'); };

function showFrame(f) {
  const img = $('frame');
  img.onload = () => { painted(f); ack(); };
  img.onerror = ack;
  img.src = `data:image/png;base64,${f.png_base64}`;
  rig.lastFrame = f;
  overlay(f);
  liveTargets(f);
  if (f.stage_um.axis_um !== undefined) $('pos-axis').textContent = num(f.stage_um.axis_um, 1);
  if (f.stage_um.piezo_um !== undefined) $('pos-piezo').textContent = num(f.stage_um.piezo_um, 2);
}

// Grab-to-paint latency and frame rate, over the last 50 frames and 2 s.
function painted(f) {
  const now = Date.now();
  rig.frames += 1;
  rig.paintedSequence = f.sequence;
  rig.latencies.push(now - f.t_unix_s * 1000);
  if (rig.latencies.length > 50) rig.latencies.shift();
  rig.paints.push(now);
  while (rig.paints.length && rig.paints[0] < now - 2000) rig.paints.shift();
  rig.fps = rig.paints.length / 2;
  const s = [...rig.latencies].sort((a, b) => a - b);
  rig.latencyMedianMs = s[Math.floor(s.length / 2)];
  $('view-stats').textContent =
    `frame ${f.sequence} · ${rig.fps.toFixed(1)} fps · grab to paint ${rig.latencyMedianMs.toFixed(0)} ms (median)`;
}

function overlay(f) {
  const svg = $('overlay');
  svg.setAttribute('viewBox', `0 0 ${f.width} ${f.height}`);
  const px = (p) => [(p[0] - f.crop[0]) * f.scale, (p[1] - f.crop[1]) * f.scale];
  svg.innerHTML = f.targets.map((t, i) => {
    const [x, y] = px(t.centre_px);
    const ro = t.outer_radius_px * f.scale, ri = t.inner_radius_px * f.scale;
    // The inner centre: the outer one plus the offset, back in px.
    const k = t.centre_px[0] ? t.centre_um[0] / t.centre_px[0] : 1;
    const xi = x + t.offset_um[0] / k * f.scale, yi = y + t.offset_um[1] / k * f.scale;
    return `<circle class="outer" cx="${x}" cy="${y}" r="${ro}"/>` +
      `<circle class="inner" cx="${xi}" cy="${yi}" r="${ri}"/>` +
      `<line x1="${x - 4}" y1="${y}" x2="${x + 4}" y2="${y}"/><line x1="${x}" y1="${y - 4}" x2="${x}" y2="${y + 4}"/>` +
      `<line x1="${xi - 3}" y1="${yi - 3}" x2="${xi + 3}" y2="${yi + 3}"/>` +
      `<text x="${x + ro + 2}" y="${y}">${esc(targetName(t, i))}</text>`;
  }).join('');
}

// The live offset's spread: the standard deviation of the last 20 frames' offsets.
function spread(name, off) {
  const h = rig.history[name] = (rig.history[name] || []).concat([off]).slice(-20);
  if (h.length < 2) return [NaN, NaN];
  return [0, 1].map((c) => {
    const m = h.reduce((a, o) => a + o[c], 0) / h.length;
    return Math.sqrt(h.reduce((a, o) => a + (o[c] - m) ** 2, 0) / (h.length - 1));
  });
}

function liveTargets(f) {
  const rows = f.targets.map((t, i) => {
    const n = targetName(t, i);
    const sd = spread(n, t.offset_um);
    const best = rig.best[n] = Math.max(rig.best[n] || 0, t.focus || 0);
    const bar = t.focus ? Math.round(100 * t.focus / best) : 0;
    return `<tr><td>${esc(n)}</td><td>${num(t.offset_um[0], 2)}, ${num(t.offset_um[1], 2)}</td>` +
      `<td>${num(sd[0], 2)}, ${num(sd[1], 2)}</td>` +
      `<td><span class="bar"><span data-w="${bar}"></span></span> ${num(t.focus, 3)}</td>` +
      `<td>${num(t.edge_sigma_px, 2)}${t.error ? ` <span class="err">${esc(t.error)}</span>` : ''}</td></tr>`;
  });
  const body = $('live-targets').tBodies[0];
  body.innerHTML = rows.join('') || '<tr><td colspan="5" class="muted">no target found</td></tr>';
  body.querySelectorAll('[data-w]').forEach((s) => { s.style.width = `${s.dataset.w}%`; });
  const zoom = $('zoom');
  const names = [''].concat(f.targets.map(targetName));
  if (zoom.options.length !== names.length || [...zoom.options].some((o, i) => o.value !== names[i])) {
    zoom.innerHTML = names.map((n) => `<option value="${esc(n)}">${n ? esc(n) : 'whole frame'}</option>`).join('');
    zoom.value = rig.zoom;
  }
}

$('view-pause').onclick = () => {
  rig.paused = !rig.paused;
  $('view-pause').textContent = rig.paused ? 'Resume picture' : 'Pause picture';
  sendView();
};
$('zoom').onchange = (e) => { rig.zoom = e.target.value; sendView(); };

// ---- the rig: state, positions, controls ----
async function refreshRig() {
  try {
    // The position first, then the status: asked together, the status could catch the
    // page's own position read and show the rig busy until the next refresh.
    const p = await api({ kind: 'position' });
    const s = await api({ kind: 'status' });
    if (s.ok) { rig.status = s.result; rig.state = s.result.rig_state; }
    else if (s.error) throw new Error(s.error.message);
    if (p.ok) showPosition(p.result);
    showRigState();
    showQueue();
  } catch (e) {
    rig.state = null;
    setDaemon('down', String(e.message || e));
  }
}

function showPosition(p) {
  rig.position = p;
  if (p.axis) $('pos-axis').textContent = num(p.axis.position_um, 1);
  if (p.piezo) $('pos-piezo').textContent = num(p.piezo.position_um, 2);
  $('pos-source').textContent = p.source ? `(${p.source})` : '';
}

function stateText(st) {
  if (!st) return 'unknown';
  if (st.state === 'busy') {
    if (st.job_id) return `busy: job ${st.job_id}`;
    if (st.request) return `busy: ${st.request}`;
    return 'busy';
  }
  if (st.state === 'fault') return `fault: ${st.device || ''}: ${st.reason || ''}`;
  return st.state;
}

function showRigState() {
  const st = rig.state;
  const b = $('rig-state');
  b.className = `badge ${st ? st.state : ''}`;
  b.textContent = `rig: ${st ? st.state : '?'}`;
  $('rig-reason').textContent = st && st.state !== 'ready' ? stateText(st) +
    (st.clear_with ? ` (clear with: ${st.clear_with.join(', ')})` : '') : '';
  updateControls();
}

// Why the daemon would refuse each control now (null: it would not).
function refusal(ctl) {
  if (rig.daemon !== 'up') return 'the daemon is not reachable';
  const st = rig.state;
  if (!st) return 'the rig state is not known yet';
  const clear = st.clear_with || [];
  switch (ctl) {
    case 'stop': return rig.moving ? null : 'no manual move under way';
    case 'unlock': case 'reconnect':
      if (st.state !== 'fault') return 'the rig is not in fault';
      return clear.includes(ctl) ? null : `this fault clears with ${clear.join(' or ')}`;
    case 'home':
      if (st.state === 'fault') return clear.includes('home') ? null : `this fault clears with ${clear.join(' or ')}`;
      break;
    case 'submit': case 'calibrate':
      if (st.state === 'fault') return `the rig is in fault (${st.reason || st.device}): clear it first`;
      return null;
    default: break;
  }
  if (rig.moving) return 'a manual move is under way';
  if (st.state === 'fault') return `the rig is in fault (${st.reason || st.device})`;
  // A read of the positions (another client's) is over in a moment, and the daemon runs a
  // rig request sent meanwhile after it: nothing to refuse.
  const reading = st.state === 'busy' && !st.job_id && st.request === 'position';
  if (st.state === 'busy' && !reading) return st.job_id ? `job ${st.job_id} is running (pause or cancel it)` : `the rig is busy${st.request ? ` (${st.request})` : ''}`;
  return null;
}

const CONTROLS = {
  'jog-axis-minus': 'move', 'jog-axis-plus': 'move', 'jog-piezo-minus': 'move',
  'jog-piezo-plus': 'move', 'move-go': 'move', stop: 'stop', home: 'home',
  unlock: 'unlock', reconnect: 'reconnect', 'f-submit': 'submit', 'cal-run': 'calibrate',
};

function updateControls() {
  const whys = new Set();
  for (const [id, ctl] of Object.entries(CONTROLS)) {
    let why = refusal(ctl);
    if (!why && id.includes('piezo') && rig.position && !rig.position.piezo) why = 'this rig has no piezo';
    const el = $(id);
    el.disabled = !!why;
    el.title = why || '';
    if (why && ctl !== 'stop' && ctl !== 'submit' && ctl !== 'calibrate') whys.add(`${el.textContent.trim()}: ${why}`);
  }
  $('rig-why').textContent = [...whys].slice(0, 3).join(' · ');
}

async function rigRequest(req) {
  $('rig-error').textContent = '';
  const moving = req.kind === 'move';
  if (moving) { rig.moving = true; updateControls(); }
  try {
    const r = await api(req);
    if (!r.ok) $('rig-error').textContent = `${req.kind}: ${r.error.message}`;
    else if (r.result && r.result.position_um !== undefined) {
      const id = r.result.stage === 'piezo' ? 'pos-piezo' : 'pos-axis';
      $(id).textContent = num(r.result.position_um, r.result.stage === 'piezo' ? 2 : 1);
    }
  } finally {
    if (moving) rig.moving = false;
    refreshRig();
  }
}

function jog(stage, sign) {
  const step = parseFloat($('jog-step').value);
  if (!isFinite(step) || step <= 0) { $('rig-error').textContent = 'step: a positive number of µm'; return; }
  rigRequest({ kind: 'move', stage, by_um: sign * step });
}
$('jog-axis-minus').onclick = () => jog('axis', -1);
$('jog-axis-plus').onclick = () => jog('axis', 1);
$('jog-piezo-minus').onclick = () => jog('piezo', -1);
$('jog-piezo-plus').onclick = () => jog('piezo', 1);
$('move-go').onclick = () => {
  const to = parseFloat($('move-to').value);
  if (!isFinite(to)) { $('rig-error').textContent = 'move to: a position in µm'; return; }
  rigRequest({ kind: 'move', stage: $('move-stage').value, to_um: to });
};
$('stop').onclick = () => api({ kind: 'stop' });
for (const k of ['home', 'unlock', 'reconnect']) {
  $(k).onclick = () => {
    const st = rig.state;
    rigRequest(st && st.state === 'fault' && st.device ? { kind: k, stage: st.device } : { kind: k });
  };
}

// ---- jobs: the form and the queue ----
function showPlanFields() {
  const plan = $('f-plan').value;
  document.querySelectorAll('.plan-scan, .plan-line, .plan-grid, .plan-list').forEach((el) => {
    el.hidden = !el.classList.contains(`plan-${plan}`);
  });
}
$('f-plan').onchange = showPlanFields;

class FieldError extends Error { constructor(field, msg) { super(msg); this.field = field; } }

// A number field's value (undefined when empty); a FieldError naming it when not a number.
function field(id, key, int) {
  const v = $(id).value.trim();
  if (v === '') return undefined;
  const n = Number(v);
  if (!isFinite(n) || (int && !Number.isInteger(n))) throw new FieldError(key, `${key}: ${JSON.stringify(v)} is not ${int ? 'a whole number' : 'a number'}`);
  return n;
}

function line(prefix, key) {
  return { stage: $(`${prefix}-stage`).value, steps: field(`${prefix}-steps`, `${key}.steps`, true), step_um: field(`${prefix}-step_um`, `${key}.step_um`) };
}

function jobOf() {
  const plan = $('f-plan').value;
  const job = {
    k: field('f-k', 'k', true), settle_ms: field('f-settle_ms', 'settle_ms', true),
    repeats: field('f-repeats', 'repeats', true), process: $('f-process').checked,
    estimator: $('f-estimator').value || undefined, registration: $('f-registration').value || undefined,
    label: $('f-label').value || undefined,
  };
  const start = field('f-start_um', 'start_um');
  if (plan === 'scan') {
    Object.assign(job, { stage: $('f-stage').value, steps: field('f-steps', 'steps', true), step_um: field('f-step_um', 'step_um'), start_um: start });
  } else if (plan === 'line') {
    job.plan = { line: { stage: $('f-stage').value, steps: field('f-steps', 'steps', true), step_um: field('f-step_um', 'step_um'), start_um: start } };
  } else if (plan === 'grid') {
    job.plan = { grid: { inner: line('f-inner', 'plan.grid.inner'), outer: line('f-outer', 'plan.grid.outer'), snake: $('f-snake').checked } };
  } else {
    job.plan = { list: $('f-list').value.split('\n').filter((l) => l.trim()).map((l, i) => {
      const [a, p] = l.split(',').map((s) => s.trim());
      const pt = {};
      if (a) pt.axis_um = Number(a);
      if (p) pt.piezo_um = Number(p);
      if (Object.values(pt).some((x) => !isFinite(x))) throw new FieldError('plan.list', `plan.list[${i}]: ${JSON.stringify(l)} is not axis_um[, piezo_um]`);
      return pt;
    }) };
  }
  return JSON.parse(JSON.stringify(job));
}

// The form's field a daemon message names: the longest field key found in it.
function fieldOf(message) {
  const keys = [...document.querySelectorAll('#job-form .err[data-field]')].map((e) => e.dataset.field)
    .sort((a, b) => b.length - a.length);
  const named = (message.match(/`([a-z_.\[\]0-9]+)`/g) || []).map((s) => s.slice(1, -1));
  for (const n of named) { const k = keys.find((k) => n === k || n.startsWith(`${k}.`) || n.startsWith(`${k}[`) || n.startsWith(`job.${k}`)); if (k) return k; }
  return keys.find((k) => new RegExp(`(^|[^a-z_.])${k.replace(/\./g, '\\.')}([^a-z_]|$)`).test(message)) || null;
}

function showFormError(message) {
  const f = fieldOf(message);
  const el = f && document.querySelector(`#job-form .err[data-field="${f}"]`);
  (el || $('f-error')).textContent = message;
}

$('job-form').onsubmit = async (e) => {
  e.preventDefault();
  document.querySelectorAll('#job-form .err').forEach((el) => { el.textContent = ''; });
  $('f-ok').textContent = '';
  let job;
  try { job = jobOf(); } catch (err) { showFormError(err.message); return; }
  const r = await api({ kind: 'submit', job });
  if (r.ok) { $('f-ok').textContent = `job ${r.result.job_id} queued (${r.result.total_frames} frames)`; refreshRig(); }
  else showFormError(r.error.message);
};

function eta(j) {
  if (j.state === 'queued' && j.starts_in_s !== undefined) return `starts in ${num(j.starts_in_s, 0)} s`;
  return j.eta_s !== undefined ? `${num(j.eta_s, 0)} s` : '–';
}

// The queue's rows are rebuilt only when its jobs or their states change; progress and ETA
// are updated in place, so a button is never replaced under the pointer.
let queueShape = null;

function showQueue() {
  const s = rig.status;
  if (!s) return;
  const jobs = (s.running ? [s.running] : []).concat(s.queued_jobs || []);
  const shape = jobs.map((j) => `${j.job_id}:${j.state}`).join(',');
  if (shape !== queueShape) {
    queueShape = shape;
    $('queue').tBodies[0].innerHTML = jobs.map(queueRow).join('') ||
      '<tr><td colspan="5" class="muted">no job running or queued</td></tr>';
    $('queue').querySelectorAll('button[data-id]').forEach(jobButton);
  }
  for (const j of jobs) {
    const tr = $('queue').querySelector(`tr[data-job="${j.job_id}"]`);
    if (!tr) continue;
    const pct = j.total_frames ? Math.round(100 * j.frames_done / j.total_frames) : 0;
    tr.querySelector('[data-w]').style.width = `${pct}%`;
    tr.querySelector('.job-frames').textContent = `${j.frames_done}/${j.total_frames}`;
    tr.querySelector('.job-eta').textContent = eta(j);
  }
}

function queueRow(j) {
  const act = j.state === 'paused' ? 'resume' : 'pause';
  return `<tr data-job="${j.job_id}"><td>${j.job_id}${j.label ? ` ${esc(j.label)}` : ''}</td><td class="job-state">${j.state}</td>` +
    '<td><span class="bar"><span data-w></span></span> <span class="job-frames"></span></td>' +
    `<td class="job-eta"></td><td>${j.state === 'queued' ? '' : `<button class="job-${act}" data-id="${j.job_id}">${act}</button>`}` +
    ` <button class="job-cancel" data-id="${j.job_id}">cancel</button></td></tr>`;
}

function jobButton(b) {
  const kind = b.className.replace('job-', '');
  b.onclick = async () => {
    const r = await api({ kind, job_id: Number(b.dataset.id) });
    $('queue-error').textContent = r.ok ? '' : `${kind} job ${b.dataset.id}: ${r.error.message}`;
    refreshRig();
  };
}

let refreshTimer = null;
function onJobEvent(e) {
  if (e.event === 'step' && rig.status && rig.status.running && rig.status.running.job_id === e.job_id) {
    rig.status.running.frames_done = e.index + 1;
    showQueue();
  }
  if (e.event === 'calibration' && e.warnings) $('cal-warnings').textContent = e.warnings.join(' · ');
  if (['finished', 'failed', 'cancelled', 'calibrated'].includes(e.event)) refreshAll();
  else if (!refreshTimer) refreshTimer = setTimeout(() => { refreshTimer = null; refreshRig(); }, 300);
}

// ---- results ----
async function refreshSessions() {
  const r = await api({ kind: 'list', limit: 30 });
  if (!r.ok) return;
  $('sessions').tBodies[0].innerHTML = r.result.sessions.map((s) =>
    `<tr data-session="${esc(s.name)}"${s.name === rig.session ? ' class="sel"' : ''}><td>${esc(s.name)}</td><td>${esc(s.started_at || '')}</td>` +
    `<td>${esc(s.label || s.replay_of || '')}</td><td>${s.frames_captured}/${s.total_frames}</td>` +
    `<td>${esc(s.state)}${s.reason ? `: ${esc(s.reason)}` : ''}</td></tr>`).join('');
  $('sessions').querySelectorAll('tr[data-session]').forEach((tr) => { tr.onclick = () => showSession(tr.dataset.session); });
}

function stds(rows) {
  const by = {};
  for (const r of rows) (by[r.target] = by[r.target] || []).push(r);
  const out = {};
  for (const [t, rs] of Object.entries(by)) {
    out[t] = ['dx_um', 'dy_um'].map((c) => {
      if (rs.length < 2) return NaN;
      const m = rs.reduce((a, r) => a + r[c], 0) / rs.length;
      return Math.sqrt(rs.reduce((a, r) => a + (r[c] - m) ** 2, 0) / (rs.length - 1));
    });
  }
  return out;
}

async function showSession(name) {
  rig.session = name;
  $('session-view').hidden = false;
  $('session-name').textContent = name;
  $('dl-csv').href = withToken(`/files/${encodeURIComponent(name)}/results.csv`);
  $('dl-tiff').href = withToken(`/files/${encodeURIComponent(name)}/export.ome.tif`);
  document.querySelectorAll('#sessions tr').forEach((tr) => tr.classList.toggle('sel', tr.dataset.session === name));
  const [t, c] = await Promise.all([
    getJson(`/api/sessions/${encodeURIComponent(name)}/targets`),
    getJson(`/api/sessions/${encodeURIComponent(name)}/charts`),
  ]);
  const rows = t.rows || [];
  const sd = stds(rows);
  $('targets').tBodies[0].innerHTML = rows.map((r) =>
    `<tr><td>${r.run}</td><td>${esc(r.case)}</td><td>${esc(r.target)}</td>` +
    `<td>${num(r.dx_um, 2)} ± ${num(r.u_dx_um, 2)}</td><td>${num(r.dy_um, 2)} ± ${num(r.u_dy_um, 2)}</td>` +
    `<td>${num(sd[r.target][0], 2)}, ${num(sd[r.target][1], 2)}</td><td>${num(r.nominal_dx_um, 1)}, ${num(r.nominal_dy_um, 1)}</td></tr>`).join('');
  $('session-note').textContent = t.error ? t.error.message : `${rows.length} measurements`;
  $('charts').innerHTML = (c.charts || []).map((s) =>
    `<img class="chart" alt="${esc(s)}" src="${withToken(`/plots/${encodeURIComponent(name)}/${encodeURIComponent(s)}.svg`)}">`).join('');
}

// ---- calibration ----
async function refreshCalibration() {
  const r = await getJson('/api/calibration');
  const c = r.current;
  if (!c) { $('cal-record').textContent = r.error ? `unusable: ${r.error}` : 'no current calibration'; return; }
  $('cal-record').innerHTML = `<b>${esc(c.id)}</b> of ${esc(c.date)} (${num(c.age_days, 1)} days old), ` +
    `${c.frames} frames ${num(c.step_um, 0)} µm apart; field residual ${num(c.residual_rms_um, 3)} µm RMS, ` +
    `${num(c.residual_max_um, 3)} µm max; ${c.rejected} rejected`;
}
$('cal-run').onclick = async () => {
  const r = await api({ kind: 'submit', job: { calibrate: {}, label: 'calibration' } });
  $('cal-msg').textContent = r.ok ? `calibration job ${r.result.job_id} queued` : r.error.message;
  refreshRig();
};

function refreshAll() {
  refreshRig();
  refreshSessions();
  refreshCalibration().catch(() => {});
}

showPlanFields();
updateControls();
connect();
setInterval(refreshRig, 1000);

// The ops page: job counts, charts of the queue depth (sampled while the page is open) and of job
// durations, jobs with their errors (retry a failed one, admin), the dirty tiles.
import './style.css';
import { api, el, fmt, setupKeyForm } from './api.js';
import { drawChart } from './chart.js';

const REFRESH_MS = 5000;
const MAX_SAMPLES = 360; // the queue chart's last 30 min at REFRESH_MS
const DEPTH_SERIES = [['queued', '#4dabf7'], ['running', '#fab005'], ['dirty_tiles', '#adb5bd']];
const DURATION_SERIES = [['done', '#40c057'], ['failed', '#fa5252']];
const samples = []; // [{t_ms, queued, running, dirty_tiles}], one per refresh
const message = (text, isError = false) => {
  const span = document.getElementById('ops-message');
  span.textContent = text;
  span.className = isError ? 'error' : 'muted';
};
const time = (iso) => (iso ? iso.slice(0, 19).replace('T', ' ') : '');

async function loadSummary() {
  const s = await api('/v1/jobs/summary');
  samples.push({ t_ms: Date.now(), ...Object.fromEntries(DEPTH_SERIES.map(([k]) => [k, Number(s[k]) || 0])) });
  samples.splice(0, samples.length - MAX_SAMPLES);
  drawChart(document.getElementById('depth-chart'),
    DEPTH_SERIES.map(([name, color]) => ({ name, color, points: samples.map((p) => [p.t_ms, p[name]]) })));
  document.getElementById('summary').replaceChildren(
    ...['queued', 'running', 'failed', 'dirty_tiles'].map((k) =>
      el('div', { class: `card ${k}`, 'data-count': k }, el('div', { class: 'n' }, s[k]), el('div', { class: 'muted' }, k.replace('_', ' ')))),
  );
}

async function loadJobs() {
  const state = document.getElementById('state-filter').value;
  const { jobs, queues } = await api(`/v1/jobs?limit=200${state ? `&state=${state}` : ''}`);
  const states = ['queued', 'running', 'failed', 'done'];
  document.getElementById('queues').replaceChildren(
    el('tr', {}, el('th', {}, 'queue'), ...states.map((s) => el('th', {}, s))),
    ...Object.entries(queues || {}).map(([queue, counts]) =>
      el('tr', { 'data-queue': queue }, el('td', {}, queue), ...states.map((s) => el('td', { class: counts[s] && s !== 'done' ? `state-${s}` : '' }, counts[s] ?? 0)))),
  );
  // each finished job listed: its duration at the time it finished
  drawChart(document.getElementById('duration-chart'), DURATION_SERIES.map(([name, color]) => ({
    name, color, dots: true,
    points: jobs.filter((j) => j.state === name && j.finished_at && j.duration_s !== null)
      .map((j) => [Date.parse(j.finished_at), j.duration_s]), // ISO 8601 with its offset
  })), { unit: ' s' });
  document.querySelector('#jobs tbody').replaceChildren(
    ...jobs.map((job) => el('tr', { 'data-job': job.id, 'data-state': job.state },
      el('td', {}, time(job.created_at)), el('td', {}, job.kind), el('td', { class: 'mono' }, job.subject),
      el('td', { class: `state-${job.state}` }, job.state), el('td', {}, job.attempts),
      el('td', {}, job.duration_s === null ? '' : `${fmt(job.duration_s)} s`),
      el('td', { class: 'error-text' }, job.error ?? ''),
      el('td', {}, job.state !== 'failed' ? '' : job.retried_by
        ? el('span', { class: 'muted', title: job.retried_by }, 'retried')
        : el('button', { type: 'button', onclick: () => retry(job) }, 'retry')))),
  );
}

async function loadDirty() {
  const { tiles } = await api('/v1/tiles/dirty');
  document.querySelector('#dirty tbody').replaceChildren(
    ...tiles.map((t) => el('tr', { 'data-tile': t.tile },
      el('td', {}, el('a', { href: `../viewer/#17/${tileCentre(t).join('/')}` }, t.tile)), el('td', {}, t.pending_trips),
      el('td', {}, time(t.first_marked_at)), el('td', {}, time(t.last_marked_at)),
      el('td', { class: 'mono' }, t.job_id ? `${t.job_id.slice(0, 8)} ${t.job_state ?? ''}` : 'waiting (quiet period)'))),
  );
}

function tileCentre({ z, x, y }) {
  const n = 2 ** z;
  const lon = ((x + 0.5) / n) * 360 - 180;
  const lat = (Math.atan(Math.sinh(Math.PI * (1 - (2 * (y + 0.5)) / n))) * 180) / Math.PI;
  return [lat.toFixed(6), lon.toFixed(6)];
}

async function retry(job) {
  try {
    const answer = await api(`/v1/jobs/${job.id}/retry`, { method: 'POST' });
    message(`retrying ${job.kind} ${job.subject} as job ${answer.id}`);
  } catch (err) {
    message(`retry: ${err.message}`, true);
  }
  await refresh();
}

async function refresh() {
  try {
    await Promise.all([loadSummary(), loadJobs(), loadDirty()]);
    document.body.dataset.loaded = String(Date.now());
  } catch (err) {
    message(err.message, true);
  }
}

document.getElementById('refresh').addEventListener('click', refresh);
document.getElementById('state-filter').addEventListener('change', refresh);
let timer = null;
function start() {
  refresh();
  clearInterval(timer);
  timer = setInterval(refresh, REFRESH_MS);
}
if (setupKeyForm(start)) start();

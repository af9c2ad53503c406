// Small time-series charts drawn as SVG (no charting library): lines of samples over time, or dots.

const NS = 'http://www.w3.org/2000/svg';
const W = 420;
const H = 150;
const PAD = { left: 40, right: 10, top: 10, bottom: 22 };

const svgEl = (tag, attrs = {}, text) => {
  const node = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text !== undefined) node.textContent = text;
  return node;
};

/** Up to ``n`` round steps (1, 2 or 5 x 10^k) from 0 to at least ``max``. */
function ticks(max, n = 4) {
  const raw = Math.max(max, 1e-9) / n;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
  return Array.from({ length: Math.ceil(max / step) + 1 }, (_, i) => i * step);
}

const clock = (ms) => new Date(ms).toTimeString().slice(0, 8);

/** Draw ``series`` ([{name, color, points: [[t_ms, value], ...], dots}]) into the <svg> ``svg``;
 * ``unit`` labels the y axis. Lines join a series' points in time order; ``dots`` draws points only. */
export function drawChart(svg, series, { unit = '' } = {}) {
  const all = series.flatMap((s) => s.points);
  svg.setAttribute('viewBox', `0 0 ${W} ${H}`);
  svg.replaceChildren();
  if (!all.length) {
    svg.append(svgEl('text', { x: W / 2, y: H / 2, 'text-anchor': 'middle', class: 'axis' }, 'no samples yet'));
    return;
  }
  const t0 = Math.min(...all.map((p) => p[0]));
  const t1 = Math.max(...all.map((p) => p[0]), t0 + 1000);
  const yTicks = ticks(Math.max(...all.map((p) => p[1]), 1));
  const yMax = yTicks[yTicks.length - 1];
  const x = (t) => PAD.left + ((t - t0) / (t1 - t0)) * (W - PAD.left - PAD.right);
  const y = (v) => H - PAD.bottom - (v / yMax) * (H - PAD.top - PAD.bottom);
  for (const v of yTicks) {
    svg.append(svgEl('line', { x1: PAD.left, x2: W - PAD.right, y1: y(v), y2: y(v), class: 'grid' }),
      svgEl('text', { x: PAD.left - 4, y: y(v) + 3, 'text-anchor': 'end', class: 'axis' }, `${+v.toPrecision(3)}${unit}`));
  }
  svg.append(svgEl('text', { x: PAD.left, y: H - 6, class: 'axis' }, clock(t0)),
    svgEl('text', { x: W - PAD.right, y: H - 6, 'text-anchor': 'end', class: 'axis' }, clock(t1)));
  for (const s of series) {
    const pts = s.points.slice().sort((a, b) => a[0] - b[0]);
    const g = svgEl('g', { 'data-series': s.name, 'data-samples': pts.length, fill: s.color, stroke: s.color });
    if (!s.dots && pts.length > 1) {
      g.append(svgEl('polyline', { points: pts.map(([t, v]) => `${x(t).toFixed(1)},${y(v).toFixed(1)}`).join(' '), fill: 'none', 'stroke-width': 1.5 }));
    }
    for (const [t, v] of pts) g.append(svgEl('circle', { cx: x(t).toFixed(1), cy: y(v).toFixed(1), r: s.dots ? 2.5 : 1.5, stroke: 'none' }));
    svg.append(g);
  }
}

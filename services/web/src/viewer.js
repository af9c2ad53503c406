// The map viewer: the service's vector tiles on a plain background, a tile's version history with
// the diff to the previous version, the lines the merge held back from it, trip trajectories (raw
// GNSS vs aligned), element details, and the human-correction actions (admin). All data comes from the CSR API; nothing from the internet.
import * as maplibregl from 'maplibre-gl';
import 'maplibre-gl/dist/maplibre-gl.css';
import './style.css';
import { api, apiKey, el, fmt, setupKeyForm } from './api.js';

maplibregl.setWorkerUrl(new URL(__WORKER_FILE__, import.meta.url).href);

// --- element styles ------------------------------------------------------------------------------

const STYLE = {
  lane_divider: { color: '#f1f3f5', width: 1.6, label: 'lane divider (dashed where dashed)' },
  road_boundary: { color: '#ff922b', width: 2.6, label: 'road boundary' },
  centerline: { color: '#4dabf7', width: 1, label: 'centerline' },
  stop_line: { color: '#ff6b6b', width: 4, label: 'stop line' },
  crosswalk: { color: '#e9ecef', fill: 0.35, label: 'crosswalk' },
  road_marking: { color: '#ffd43b', fill: 0.6, label: 'road marking' },
};
// validator flags by level (the TileJSON's ``flag_levels``: kind -> severe | warning | info, see
// docs/viewer.md): a feature shows its most severe flag; only severe ones glow strongly, a warning
// gets a thin halo, an informative flag (or a kind the table does not name) a faint line
const FLAG_LEVELS = [
  { level: 'info', rank: 0, color: '#748ffc', width: 4, opacity: 0.3, blur: 0, label: 'validator flag: informative' },
  { level: 'warning', rank: 1, color: '#fcc419', width: 6, opacity: 0.45, blur: 1, label: 'validator flag: warning' },
  { level: 'severe', rank: 2, color: '#f06595', width: 14, opacity: 0.75, blur: 3, label: 'validator flag: severe' },
];
const LEVEL_RANK = Object.fromEntries(FLAG_LEVELS.map((l) => [l.level, l.rank]));
const TRACK_COLORS = { raw: '#da77f2', aligned: '#69db7c' };
const DIFF_COLORS = { added: '#40c057', modified: '#fab005', removed: '#fa5252' };
const HELD_BACK_COLOR = '#adb5bd';

const byType = (type, sourceLayer) => (sourceLayer === type ? null : ['==', ['get', 'type'], type]);
const all = (...filters) => {
  const parts = filters.filter(Boolean);
  return parts.length ? ['all', ...parts] : undefined;
};
// validator flags: a list in GeoJSON, its JSON text in a vector tile (which carries scalars only);
// either way ``to-string`` gives '["kind", ...]', in which a kind is found with its quotes
const FLAG_TEXT = ['to-string', ['get', 'flags']];
const FLAGGED = ['all', ['has', 'flags'], ['!', ['in', FLAG_TEXT, ['literal', ['', '[]']]]]];

/** The rank of a feature's most severe flag (``levels``: kind -> level); 0 (info) for kinds it does not name. */
function flagRank(levels) {
  const known = Object.entries(levels).map(([kind, level]) => ['case', ['in', JSON.stringify(kind), FLAG_TEXT], LEVEL_RANK[level] ?? 0, 0]);
  return ['max', 0, ...known];
}

/** A flag paint property (FLAG_LEVELS' ``key``) stepped by the rank. */
const byLevel = (rank, key) => ['step', rank, FLAG_LEVELS[0][key], ...FLAG_LEVELS.slice(1).flatMap((l) => [l.rank, l[key]])];

/** The flag layers' paint: colour, width, opacity and blur by the feature's most severe flag. */
function flagPaint(levels) {
  const rank = flagRank(levels);
  return {
    'line-color': byLevel(rank, 'color'),
    'line-width': byLevel(rank, 'width'),
    'line-opacity': byLevel(rank, 'opacity'),
    'line-blur': byLevel(rank, 'blur'),
  };
}

/** The style layers of the road structure in one source (a vector layer, or GeoJSON). */
function elementLayers(prefix, source, sourceLayer) {
  const base = (id, type, filter, paint, layout) => {
    const layer = { id: `${prefix}-${id}`, type, source, paint, layout: layout || {} };
    if (sourceLayer) layer['source-layer'] = sourceLayer;
    if (filter) layer.filter = filter;
    return layer;
  };
  const line = (type, extra, paint) =>
    base(`${type}${extra?.name ? '-' + extra.name : ''}`, 'line', all(byType(type, sourceLayer), extra?.filter), {
      'line-color': STYLE[type].color,
      'line-width': STYLE[type].width,
      ...paint,
    }, { 'line-cap': 'butt', 'line-join': 'round' });
  const dashed = ['==', ['get', 'style'], 'dashed'];
  const DERIVED = ['has', 'derived']; // centrelines derived from dividers and boundaries or trip paths
  return [
    base('flags', 'line', FLAGGED, flagPaint(state.flagLevels)),
    ...['crosswalk', 'road_marking'].flatMap((type) => [
      base(`${type}-fill`, 'fill', byType(type, sourceLayer), { 'fill-color': STYLE[type].color, 'fill-opacity': STYLE[type].fill }),
      base(`${type}-outline`, 'line', byType(type, sourceLayer), { 'line-color': STYLE[type].color, 'line-width': 1 }),
    ]),
    line('road_boundary'),
    line('centerline', { filter: ['!', DERIVED] }, { 'line-opacity': 0.8 }),
    line('centerline', { name: 'derived', filter: DERIVED }, { 'line-opacity': 0.8, 'line-dasharray': [1, 2] }),
    line('lane_divider', { name: 'solid', filter: ['!', dashed] }),
    line('lane_divider', { name: 'dashed', filter: dashed }, { 'line-dasharray': [3, 3] }),
    line('stop_line'),
  ];
}

// --- state and map -------------------------------------------------------------------------------

const state = {
  tileZoom: 16,
  flagLevels: {}, // flag kind -> severe | warning | info, from the TileJSON
  openedOn: null, // 'link' (the URL's #zoom/lat/lon showed the data) or 'data' (fitted to the TileJSON bounds)
  liveLayers: [], // ids of the live (vector tile) element layers
  tile: null, // {z, x, y}
  versions: [], // of the selected tile, oldest first
  shownVersion: null,
  heldBack: null, // the held-back lines drawn (a FeatureCollection), null while the toggle is off
  tracks: new Map(), // trip id -> its FeatureCollection
  pairs: [], // the selected tile's match pairs, as listed
};

const empty = { type: 'FeatureCollection', features: [] };
// MapLibre writes the view into the hash as soon as the map moves: what the URL brought is read first
const linkedView = parseHash(location.hash);
const map = new maplibregl.Map({
  container: 'map',
  hash: true,
  center: linkedView ? [linkedView.lng, linkedView.lat] : [0, 0],
  zoom: linkedView ? linkedView.zoom : 1,
  attributionControl: false,
  style: {
    version: 8,
    sources: {
      version: { type: 'geojson', data: empty },
      diff: { type: 'geojson', data: empty },
      'held-back': { type: 'geojson', data: empty },
      tracks: { type: 'geojson', data: empty },
      selection: { type: 'geojson', data: empty },
    },
    layers: [{ id: 'background', type: 'background', paint: { 'background-color': '#15191e' } }],
  },
  // the key goes with every request to this origin (tiles included), never elsewhere
  transformRequest: (url) =>
    url.startsWith(location.origin) ? { url, headers: { Authorization: `Bearer ${apiKey()}` } } : { url },
});
map.addControl(new maplibregl.NavigationControl({ showCompass: false }), 'top-right');
map.addControl(new maplibregl.ScaleControl({ unit: 'metric' }), 'bottom-right');
window.csrViewer = { map, state }; // for the browser tests and the console

function addStaticLayers() {
  for (const [kind, color] of Object.entries(DIFF_COLORS)) {
    map.addLayer({
      id: `diff-${kind}`, type: 'line', source: 'diff', filter: ['==', ['get', 'change'], kind],
      paint: { 'line-color': color, 'line-width': 14, 'line-opacity': 0.55, 'line-blur': 3, ...(kind === 'removed' ? { 'line-dasharray': [1, 1] } : {}) },
    });
  }
  for (const layer of elementLayers('version', 'version')) map.addLayer(layer);
  map.addLayer({
    id: 'held-back', type: 'line', source: 'held-back',
    paint: { 'line-color': HELD_BACK_COLOR, 'line-width': 2.5, 'line-dasharray': [2, 2] },
  });
  for (const [kind, color] of Object.entries(TRACK_COLORS)) {
    map.addLayer({
      id: `track-${kind}`, type: 'line', source: 'tracks', filter: ['==', ['get', 'kind'], kind],
      paint: { 'line-color': color, 'line-width': kind === 'raw' ? 1.5 : 2.5, ...(kind === 'raw' ? { 'line-dasharray': [2, 2] } : {}) },
    });
  }
  map.addLayer({ id: 'selection', type: 'line', source: 'selection', paint: { 'line-color': '#ffffff', 'line-width': 1, 'line-dasharray': [4, 4] } });
}

/** ``#zoom/lat/lng[/bearing/pitch]`` (MapLibre's hash) as numbers, or null. */
function parseHash(hash) {
  const [zoom, lat, lng] = hash.replace(/^#/, '').split('/').map(Number);
  const ok = [zoom, lat, lng].every(Number.isFinite) && Math.abs(lat) <= 90 && Math.abs(lng) <= 180;
  return ok ? { zoom, lat, lng } : null;
}

// a shared link is kept when it shows the data: its view overlaps the data's bounds and is zoomed in
// no more than this many levels short of the view that fits all of it
const LINK_ZOOM_SLACK = 2;

/** Open on the data: keep the linked view when it shows the data, otherwise fit the TileJSON bounds. */
function openOnData(tilejson) {
  if (!tilejson.feature_count || !tilejson.bounds) return;
  const [west, south, east, north] = tilejson.bounds;
  const fit = map.cameraForBounds([[west, south], [east, north]], { padding: 40, maxZoom: 18 });
  if (linkedView && fit) {
    const view = map.getBounds();
    const overlaps = view.getWest() <= east && view.getEast() >= west && view.getSouth() <= north && view.getNorth() >= south;
    if (overlaps && map.getZoom() >= fit.zoom - LINK_ZOOM_SLACK) {
      state.openedOn = 'link';
      return;
    }
  }
  if (fit) map.jumpTo(fit);
  state.openedOn = 'data';
}

// a tile URL template as the TileJSON gives it (new URL() would escape its {z}/{x}/{y})
const absolute = (t) => (t.startsWith('/') ? location.origin + t : t);

/** The live map: the TileJSON's vector tiles, one set of element layers per vector layer. */
async function addLiveTiles(tilejson) {
  if (!tilejson) return;
  state.tileZoom = tilejson.pipeline_zoom ?? state.tileZoom;
  document.getElementById('map-version').textContent =
    tilejson.map_version !== undefined ? `map version ${tilejson.map_version}` : '';
  map.addSource('live', {
    type: 'vector',
    tiles: tilejson.tiles.map(absolute),
    minzoom: tilejson.minzoom ?? 0,
    maxzoom: tilejson.maxzoom ?? 16,
    ...(tilejson.bounds ? { bounds: tilejson.bounds } : {}),
  });
  const before = 'diff-added';
  for (const vl of tilejson.vector_layers || []) {
    for (const layer of elementLayers(`live-${vl.id}`, 'live', vl.id)) {
      map.addLayer(layer, before);
      state.liveLayers.push(layer.id);
    }
  }
  openOnData(tilejson);
}

/** After a new version: the TileJSON names the new map version, the live source follows it. */
async function refreshLive() {
  const tilejson = await api('/v1/tiles.json', { fresh: true }).catch(() => null);
  const source = map.getSource('live');
  if (!tilejson || !source) return;
  document.getElementById('map-version').textContent = `map version ${tilejson.map_version}`;
  source.setTiles(tilejson.tiles.map(absolute));
}

function setLiveOpacity(opacity) {
  for (const id of state.liveLayers) {
    const type = map.getLayer(id)?.type;
    if (!type) continue;
    const flagOpacity = byLevel(flagRank(state.flagLevels), 'opacity');
    if (!id.endsWith('-flags')) map.setPaintProperty(id, `${type}-opacity`, opacity);
    else map.setPaintProperty(id, 'line-opacity', opacity === 1 ? flagOpacity : ['*', opacity, flagOpacity]);
  }
}

function legend() {
  const ul = document.querySelector('#legend ul');
  const item = (color, label, { fill, dash } = {}) =>
    el('li', {}, el('span', { class: `swatch${fill ? ' fill' : ''}`, style: `border-color:${color};${fill ? `background:${color}` : ''}${dash ? ';border-top-style:dashed' : ''}` }), label);
  for (const s of Object.values(STYLE)) ul.append(item(s.color, s.label, { fill: Boolean(s.fill) }));
  ul.append(item(STYLE.centerline.color, 'centerline, derived (no perceived one)', { dash: true }),
    ...FLAG_LEVELS.slice().reverse().map((l) => item(l.color, l.label)), item(HELD_BACK_COLOR, 'held-back line (tile panel)', { dash: true }),
    item(TRACK_COLORS.raw, 'trip: raw GNSS', { dash: true }), item(TRACK_COLORS.aligned, 'trip: aligned'));
}

const setMessage = (text, isError = false) => {
  const p = document.getElementById('tile-message');
  p.textContent = text;
  p.className = isError ? 'error' : 'muted';
};

// --- tiles and versions --------------------------------------------------------------------------

function tileAt(lngLat, z) {
  const n = 2 ** z;
  const lat = (Math.max(-85.0511, Math.min(85.0511, lngLat.lat)) * Math.PI) / 180;
  const x = Math.floor(((lngLat.lng + 180) / 360) * n);
  const y = Math.floor(((1 - Math.log(Math.tan(lat) + 1 / Math.cos(lat)) / Math.PI) / 2) * n);
  return { z, x: Math.min(Math.max(x, 0), n - 1), y: Math.min(Math.max(y, 0), n - 1) };
}

/** [west, south, east, north] of a tile, degrees. */
function tileBounds({ z, x, y }) {
  const lon = (xx) => (xx / 2 ** z) * 360 - 180;
  const lat = (yy) => (Math.atan(Math.sinh(Math.PI * (1 - (2 * yy) / 2 ** z))) * 180) / Math.PI;
  return [lon(x), lat(y + 1), lon(x + 1), lat(y)];
}

function tilePolygon(tile) {
  const [w, s, e, n] = tileBounds(tile);
  const ring = [[w, n], [e, n], [e, s], [w, s], [w, n]];
  return { type: 'Feature', properties: {}, geometry: { type: 'Polygon', coordinates: [ring] } };
}

const tilePath = (t) => `/v1/tiles/${t.z}/${t.x}/${t.y}`;

async function selectTile(tile) {
  state.tile = tile;
  document.getElementById('tile-name').textContent = `${tile.z}/${tile.x}/${tile.y}`;
  map.getSource('selection').setData({ type: 'FeatureCollection', features: [tilePolygon(tile)] });
  setMessage('');
  await Promise.all([loadVersions(), loadCorrections()]);
}

async function loadVersions({ showNewest = false } = {}) {
  const box = document.getElementById('versions');
  try {
    const data = await api(`${tilePath(state.tile)}/versions`);
    state.versions = (Array.isArray(data) ? data : data.versions || []).slice().sort((a, b) => a.version - b.version);
  } catch (err) {
    state.versions = [];
    setMessage(err.status === 404 ? 'no versions for this tile' : `versions: ${err.message}`, err.status !== 404);
  }
  box.hidden = state.versions.length === 0;
  const slider = document.getElementById('version-slider');
  slider.max = String(Math.max(0, state.versions.length - 1));
  if (state.versions.length && (showNewest || state.shownVersion === null)) {
    slider.value = slider.max;
  }
  if (state.versions.length) await showVersion(Number(slider.value));
  else showLive();
}

/** Draw version ``index`` of the selected tile and its diff to the previous version. */
async function showVersion(index) {
  const entry = state.versions[index];
  const prev = state.versions[index - 1];
  const path = tilePath(state.tile);
  const fc = await api(`${path}/versions/${entry.version}`);
  let diff;
  try {
    diff = prev ? diffFeatures(await api(`${path}/diff?from=${prev.version}&to=${entry.version}`)) : changedIn(fc, 'added');
  } catch {
    diff = prev ? diffFeatures(clientDiff(await api(`${path}/versions/${prev.version}`), fc)) : changedIn(fc, 'added');
  }
  map.getSource('version').setData(fc);
  map.getSource('diff').setData(diff);
  state.shownVersion = entry.version;
  setLiveOpacity(0.15);
  const counts = Object.fromEntries(Object.keys(DIFF_COLORS).map((k) => [k, diff.features.filter((f) => f.properties.change === k).length]));
  document.getElementById('version-label').textContent =
    `v${entry.version} of ${state.versions.length} · ${entry.status ?? ''} · ${entry.reason ?? ''} · ${fc.features.length} elements · ` +
    `+${counts.added} ~${counts.modified} −${counts.removed}` + (entry.created_at ? ` · ${entry.created_at.slice(0, 19)}` : '');
  await loadHeldBack();
}

function showLive() {
  map.getSource('version').setData(empty);
  map.getSource('diff').setData(empty);
  state.shownVersion = null;
  setLiveOpacity(1);
  loadHeldBack();
}

let heldBackRequest = 0; // an answer to an older request (another tile or version) is dropped

/** While the toggle is on: ``GET .../held-back`` of the shown version (the tile's latest on the live
 * map), drawn dashed grey, with its count; a 409 (no readable state) says the lines are unknown. */
async function loadHeldBack() {
  const request = ++heldBackRequest;
  const out = document.getElementById('held-back-count');
  const show = (fc, text, isError = false) => {
    if (request !== heldBackRequest) return;
    state.heldBack = fc;
    map.getSource('held-back').setData(fc || empty);
    Object.assign(out, { textContent: text, className: isError ? 'error' : 'muted', title: fc ? `${fc.tile} v${fc.version}` : '' });
  };
  if (!document.getElementById('held-back-toggle').checked || !state.tile) return show(null, '');
  out.textContent = 'loading…';
  const query = state.shownVersion === null ? '' : `?version=${state.shownVersion}`;
  try {
    const fc = await api(`${tilePath(state.tile)}/held-back${query}`);
    show(fc, fc.features.length ? `${fc.features.length} held back` : 'none held back');
  } catch (err) {
    show(null, err.status === 409 ? `unknown: ${err.message}` : `held-back lines: ${err.message}`, err.status !== 409);
  }
}

const CHANGE_NAMES = { added: 'added', removed: 'removed', modified: 'modified', changed: 'modified' };

/** A diff entry as a GeoJSON Feature: a Feature, a brief ``{id, type, style, geometry}``, or a
 * modification ``{id, before, after}`` (drawn where it is now). */
function asFeature(item) {
  if (item?.after) item = item.after;
  if (item?.type === 'Feature') return item;
  if (!item?.geometry) return null;
  return { type: 'Feature', id: item.id, geometry: item.geometry, properties: { id: item.id, type: item.type, style: item.style } };
}

/** The diff answer as one FeatureCollection with ``properties.change``: ``{added, removed, modified}``
 * (each a list or a FeatureCollection), or a FeatureCollection whose features carry ``change``. */
function diffFeatures(data) {
  const features = [];
  const push = (item, change) => {
    const f = asFeature(item);
    if (f && CHANGE_NAMES[change]) features.push({ ...f, properties: { ...f.properties, change: CHANGE_NAMES[change] } });
  };
  if (data?.type === 'FeatureCollection') data.features.forEach((f) => push(f, f.properties?.change));
  else for (const [change, group] of Object.entries(data || {})) {
    const list = Array.isArray(group) ? group : group?.features;
    if (Array.isArray(list)) list.forEach((f) => push(f, change));
  }
  return { type: 'FeatureCollection', features };
}

const featureId = (f) => f.properties?.id ?? f.properties?.feature_id ?? f.id;
const changedIn = (fc, change) => ({ type: 'FeatureCollection', features: fc.features.map((f) => ({ ...f, properties: { ...f.properties, change } })) });

/** Fallback when the server has no diff: compare stable feature ids and geometries. */
function clientDiff(before, after) {
  const old = new Map(before.features.map((f) => [featureId(f), f]));
  const now = new Map(after.features.map((f) => [featureId(f), f]));
  const out = { added: [], removed: [], modified: [] };
  for (const [id, f] of now) {
    if (!old.has(id)) out.added.push(f);
    else if (JSON.stringify(old.get(id).geometry) !== JSON.stringify(f.geometry)) out.modified.push(f);
  }
  for (const [id, f] of old) if (!now.has(id)) out.removed.push(f);
  return out;
}

// --- element details -----------------------------------------------------------------------------

async function showElement(feature) {
  const panel = document.getElementById('element-panel');
  const box = document.getElementById('element');
  panel.hidden = false;
  const id = featureId(feature);
  let detail = { id, properties: feature.properties, history: [] };
  try {
    detail = await api(`/v1/features/${encodeURIComponent(id)}`);
  } catch (err) {
    box.dataset.error = err.message;
  }
  // a held-back line is not in the version the API describes: its own properties come first
  const heldBack = feature.properties?.status === 'held_back';
  const p = heldBack ? { ...(detail.properties || {}), ...feature.properties } : { ...feature.properties, ...(detail.properties || {}) };
  const flags = Array.isArray(p.flags) ? p.flags.join(', ') : p.flags;
  const rows = [
    ['id', detail.id ?? id], ['type', p.type], ['style', p.style],
    ['status', heldBack ? `held back: ${fmt(p.passed_trips, 0)} trips drove alongside without seeing it` : undefined],
    ['derived', p.derived ? `${p.derived === 'trip_paths' ? 'connector along the trips\' paths' : 'between dividers / boundaries'}${p.direction === 'assumed' ? ', direction assumed (nobody drove it)' : ''}` : undefined],
    ['support', `${fmt(p.support_trips, 0)} trips, ${fmt(p.support_observations, 0)} observations`],
    ['uncertainty', p.uncertainty_m !== undefined ? `${fmt(p.uncertainty_m, 3)} m` : undefined],
    ['first seen', p.first_seen], ['last confirmed', p.last_confirmed], ['flags', flags && flags !== '[]' ? flags : 'none'],
  ];
  const history = (detail.history || []).map((h) =>
    el('li', {}, `v${h.version ?? h.tile_version ?? '?'} ${h.change ?? ''} ${h.created_at ? h.created_at.slice(0, 19) : ''}`));
  box.replaceChildren(
    el('dl', {}, ...rows.filter(([, v]) => v !== undefined && v !== null).flatMap(([k, v]) => [el('dt', {}, k), el('dd', {}, v)])),
    el('h3', {}, 'history'),
    history.length ? el('ol', {}, ...history) : el('p', { class: 'muted' }, 'no history'),
  );
}

// --- corrections (admin) -------------------------------------------------------------------------

const MAX_PAIRS = 25; // listed weakest first (the API orders by confidence)
const short = (id) => (id ? String(id).slice(0, 6) : 'map');

async function loadCorrections() {
  const box = document.getElementById('corrections');
  const path = tilePath(state.tile);
  let pairs;
  try {
    pairs = await api(`${path}/match-pairs`);
  } catch (err) {
    box.hidden = true;
    if (err.status === 403) setMessage('corrections need an admin key');
    return;
  }
  box.hidden = false;
  pairs = Array.isArray(pairs) ? pairs : pairs.pairs || pairs.match_pairs || [];
  // human (added) pairs first, then weakest first as the API lists them
  state.pairs = pairs.slice().sort((a, b) => Boolean(b.human) - Boolean(a.human));
  pairs = state.pairs;
  document.getElementById('pairs').replaceChildren(
    pairs.length
      ? el('table', {}, el('tr', {}, ...['trips', 'conf.', 'rms m', 'status', ''].map((h) => el('th', {}, h))),
        ...pairs.slice(0, MAX_PAIRS).map((pair) => el('tr', {
          'data-pair': pair.id, class: ['active', 'added'].includes(pair.status) ? 'pick' : 'pick muted', title: 'click: prefill "add a pair"',
          onclick: (e) => {
            if (!e.target.closest('button')) prefillPair(pair, e.currentTarget); // not on "show" / "reject"
          },
        },
          el('td', { class: 'mono', title: `${pair.trip_i} ↔ ${pair.trip_j}` }, `${short(pair.trip_i)}↔${short(pair.trip_j)}`),
          el('td', {}, fmt(pair.confidence)), el('td', {}, fmt(pair.residual_rms_m, 3)),
          el('td', {}, pair.status, pair.human ? el('span', { class: 'human' }, ' human') : null),
          el('td', {},
            pair.centre ? el('button', { type: 'button', title: 'show on the map', onclick: () => map.flyTo({ center: pair.centre, zoom: Math.max(map.getZoom(), 18) }) }, 'show') : null,
            pair.status === 'active' || pair.status === 'added'
              ? el('button', { type: 'button', class: 'danger', onclick: () => correct({ kind: 'reject_pair', pair_id: pair.id }) }, 'reject')
              : null))))
      : el('p', { class: 'muted' }, 'no match pairs'),
    pairs.length > MAX_PAIRS ? el('p', { class: 'muted' }, `… ${pairs.length - MAX_PAIRS} more (weakest first)`) : '',
  );
  await loadPairTrips(pairs);
  let corrections = [];
  try {
    const data = await api(`/v1/corrections?z=${state.tile.z}&x=${state.tile.x}&y=${state.tile.y}`);
    corrections = Array.isArray(data) ? data : data.corrections || [];
  } catch (err) {
    corrections = [];
  }
  document.getElementById('correction-list').replaceChildren(
    corrections.length
      ? el('table', {}, ...corrections.map((c) => el('tr', { 'data-correction': c.id },
        el('td', {}, c.kind),
        el('td', { class: 'mono' }, c.kind === 'add_pair' ? `${short(c.payload.trip_i)}↔${short(c.payload.trip_j)}` : short(c.payload?.pair_id ?? c.pair_id ?? c.id)),
        el('td', { title: `by ${c.author_key_id ?? '?'} at ${c.created_at ?? ''}` }, c.result_version_id ? `→ map v${c.result_version_id}` : 'pending'),
        el('td', {}, c.undone_at ? `undone${c.undo_version_id ? ` → map v${c.undo_version_id}` : ''}` : el('button', { type: 'button', onclick: () => undo(c.id) }, 'undo')))))
      : el('p', { class: 'muted' }, 'none'),
  );
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

/** Poll ``probe`` until it returns something truthy (or give up after ``timeoutMs``). */
async function poll(probe, timeoutMs = 120000) {
  for (const deadline = Date.now() + timeoutMs; Date.now() < deadline; await sleep(700)) {
    const value = await probe().catch(() => null);
    if (value) return value;
  }
  return null;
}

/** A correction runs as a ``correct_tile`` job, then ``merge_tile`` makes the new version: wait for
 * the job, then for the correction to name its version (``field``: result_version_id or
 * undo_version_id). */
async function afterCorrection(answer, field, what) {
  const jobId = field === 'undo_version_id' ? answer.undo_job_id : answer.job_id;
  setMessage(`${what}: job ${jobId} queued…`);
  const job = await poll(async () => {
    const j = await api(`/v1/jobs/${jobId}`);
    return ['done', 'failed'].includes(j.state) && j;
  });
  let version = null;
  if (job?.state === 'done') {
    const { z, x, y } = state.tile;
    version = await poll(async () => {
      const { corrections } = await api(`/v1/corrections?z=${z}&x=${x}&y=${y}`);
      return corrections.find((c) => c.id === answer.id)?.[field];
    }, 60000);
  }
  await Promise.all([loadVersions({ showNewest: true }), loadCorrections(), refreshLive()]);
  setMessage(
    !job ? `${what}: still running` : job.state === 'failed' ? `${what}: job failed (${job.error})`
      : `${what}: job done${version ? `, map version ${version}` : ''}`,
    job?.state === 'failed',
  );
}

async function correct(body) {
  try {
    await afterCorrection(await api(`${tilePath(state.tile)}/corrections`, { method: 'POST', body }), 'result_version_id', body.kind);
  } catch (err) {
    setMessage(`${body.kind}: ${err.message}`, true);
  }
}

async function undo(correctionId) {
  try {
    await afterCorrection(await api(`/v1/corrections/${correctionId}/undo`, { method: 'POST' }), 'undo_version_id', 'undo');
  } catch (err) {
    setMessage(`undo: ${err.message}`, true);
  }
}

// --- add a pair (admin) --------------------------------------------------------------------------

const addForm = document.getElementById('add-pair');
const fields = (name) => [...addForm.querySelectorAll(`[name="${name}"]`)];
const numbers = (name) => fields(name).map((i) => (i.value.trim() === '' ? null : Number(i.value)));

/** The trip selects: the trips crossing the tile (``GET /v1/trips?bbox=``) and those its pairs name. */
async function loadPairTrips(pairs) {
  const data = await api(`/v1/trips?bbox=${tileBounds(state.tile).map((v) => v.toFixed(7)).join(',')}&limit=200`).catch(() => ({ trips: [] }));
  const names = new Map(data.trips.map((t) => [t.id, `${t.vehicle_id}/${t.trip_id}`]));
  for (const id of pairs.flatMap((p) => [p.trip_i, p.trip_j])) if (id && !names.has(id)) names.set(id, short(id));
  for (const select of [addForm.elements.trip_i, addForm.elements.trip_j]) {
    const keep = select.value;
    select.replaceChildren(...(select.name === 'trip_j' ? [el('option', { value: '' }, 'the map')] : []),
      ...[...names].map(([id, label]) => el('option', { value: id, title: id }, label)));
    if ([...select.options].some((o) => o.value === keep)) select.value = keep;
  }
  mapSide();
}

/** Trip j "the map": its frames mean nothing (sent as [0, 0]). */
const mapSide = () => fields('frames_j').forEach((i) => (i.disabled = !addForm.elements.trip_j.value));

function prefillPair(pair, row) {
  document.querySelectorAll('#pairs tr.active').forEach((r) => r.classList.remove('active'));
  row.classList.add('active');
  addForm.elements.trip_i.value = pair.trip_i;
  addForm.elements.trip_j.value = pair.trip_j ?? '';
  for (const side of ['i', 'j']) fields(`frames_${side}`).forEach((input, k) => (input.value = pair[`frames_${side}`]?.[k] ?? ''));
  mapSide();
}

async function addPair(event) {
  event.preventDefault();
  const out = document.getElementById('add-pair-message');
  const show = (text, isError) => Object.assign(out, { textContent: text, className: isError ? 'error' : 'muted' });
  addForm.querySelectorAll('.invalid').forEach((i) => i.classList.remove('invalid'));
  const tripJ = addForm.elements.trip_j.value || null;
  const body = {
    kind: 'add_pair', trip_i: addForm.elements.trip_i.value || null, frames_i: numbers('frames_i'),
    trip_j: tripJ, frames_j: tripJ ? numbers('frames_j') : [0, 0],
  };
  const offset = numbers('offset_xyyaw');
  if (offset.some((v) => v !== null)) body.offset_xyyaw = offset;
  if (addForm.elements.note.value.trim()) body.note = addForm.elements.note.value.trim();
  const button = addForm.querySelector('button[type=submit]');
  button.disabled = true;
  try {
    const answer = await api(`${tilePath(state.tile)}/corrections`, { method: 'POST', body });
    show(`correction ${answer.id} ${answer.status ?? 'queued'}: job ${answer.job_id}`);
    await afterCorrection(answer, 'result_version_id', 'add_pair');
  } catch (err) {
    // the API names the field: "trip_j", or "body.frames_i.1" for a malformed body
    const where = err.body?.location || '';
    show(where && !err.message.startsWith(where) ? `${where}: ${err.message}` : err.message, true);
    const field = where.replace(/^body\./, '').split('.')[0];
    if (field) fields(field).forEach((i) => i.classList.add('invalid'));
  } finally {
    button.disabled = false;
  }
}

// --- trips ---------------------------------------------------------------------------------------

async function loadTrips() {
  const b = map.getBounds();
  const list = document.getElementById('trips');
  try {
    const data = await api(`/v1/trips?bbox=${[b.getWest(), b.getSouth(), b.getEast(), b.getNorth()].map((v) => v.toFixed(6)).join(',')}&limit=100`);
    list.replaceChildren(...data.trips.map((trip) => el('li', {},
      el('input', { type: 'checkbox', 'data-trip': trip.id, checked: state.tracks.has(trip.id), onchange: (e) => toggleTrack(trip.id, e.target.checked) }),
      el('span', { class: 'mono', title: trip.id }, `${trip.vehicle_id}/${trip.trip_id}`),
      el('span', { class: 'muted' }, `${trip.status} ${fmt(trip.length_km)} km`))));
    if (!data.trips.length) list.replaceChildren(el('li', { class: 'muted' }, 'no trips in view'));
  } catch (err) {
    list.replaceChildren(el('li', { class: 'error' }, err.message));
  }
}

async function toggleTrack(tripId, on) {
  if (on) state.tracks.set(tripId, await api(`/v1/trips/${tripId}/track.geojson`));
  else state.tracks.delete(tripId);
  map.getSource('tracks').setData({ type: 'FeatureCollection', features: [...state.tracks.values()].flatMap((fc) => fc.features) });
}

// --- wiring --------------------------------------------------------------------------------------

const ELEMENT_LAYER = /^(live-.*|version)-(?!flags)|^held-back$/;

map.on('click', async (event) => {
  const { x, y } = event.point;
  const layers = map.getStyle().layers.map((l) => l.id).filter((id) => ELEMENT_LAYER.test(id));
  const hit = map.queryRenderedFeatures([[x - 4, y - 4], [x + 4, y + 4]], { layers })[0];
  if (hit) showElement(hit);
  const tile = tileAt(event.lngLat, state.tileZoom);
  if (!state.tile || ['z', 'x', 'y'].some((k) => tile[k] !== state.tile[k])) {
    state.shownVersion = null;
    await selectTile(tile);
  }
});
map.on('mousemove', (event) => {
  const layers = map.getStyle().layers.map((l) => l.id).filter((id) => ELEMENT_LAYER.test(id));
  const { x, y } = event.point;
  map.getCanvas().style.cursor = map.queryRenderedFeatures([[x - 4, y - 4], [x + 4, y + 4]], { layers }).length ? 'pointer' : '';
});
document.getElementById('version-slider').addEventListener('input', (e) => showVersion(Number(e.target.value)).catch((err) => setMessage(err.message, true)));
document.getElementById('live-button').addEventListener('click', showLive);
document.getElementById('held-back-toggle').addEventListener('change', loadHeldBack);
document.getElementById('trips-refresh').addEventListener('click', loadTrips);
addForm.addEventListener('submit', addPair);
addForm.elements.trip_j.addEventListener('change', mapSide);

legend();
const ready = new Promise((resolve) => map.on('load', resolve));
async function start() {
  await ready;
  if (map.getSource('live')) return;
  const tilejson = await api('/v1/tiles.json').catch((err) => setMessage(`no TileJSON (${err.message}): live tiles off`, true));
  state.flagLevels = tilejson?.flag_levels ?? {};
  if (!map.getLayer('selection')) addStaticLayers();
  await addLiveTiles(tilejson);
  document.body.dataset.ready = 'true';
}
if (setupKeyForm(start)) start();

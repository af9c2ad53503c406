// Drives Debian's headless Chromium with playwright-core (from services/web/node_modules) through
// the viewer or the ops page of a running CSR service, and prints one JSON line of what it saw.
// pytest (tests/browser/test_*.py) starts the service, seeds data, runs this and asserts.
//
//   node tests/browser/driver.mjs viewer|open|held-back|ops '{"base": "http://127.0.0.1:PORT", "key": "...", "out": "test-artifacts/browser", ...}'
import { createRequire } from 'node:module';
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';
import { fileURLToPath } from 'node:url';

const webDir = fileURLToPath(new URL('../../services/web/', import.meta.url));
const { chromium } = createRequire(join(webDir, 'package.json'))('playwright-core');

// The machine's closed network: no background connections; WebGL on the CPU (SwiftShader).
const CHROMIUM_ARGS = [
  '--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
  '--disable-background-networking', '--disable-component-update', '--disable-sync',
  '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
];

const [scenario, configJson] = process.argv.slice(2);
const config = JSON.parse(configJson);
mkdirSync(config.out, { recursive: true });
const result = { scenario, checks: {}, screenshots: [], console: [], errors: [] };
const check = (name, value) => {
  result.checks[name] = value;
};

async function shot(page, name) {
  const path = join(config.out, `${config.out_prefix || ''}${name}.png`);
  await page.screenshot({ path });
  result.screenshots.push(path);
}

/** Share of the map canvas's pixels that differ from the background colour (the map drew something). */
async function drawnShare(page) {
  const png = (await page.locator('#map').screenshot()).toString('base64');
  return page.evaluate(async (data) => {
    const img = new Image();
    img.src = `data:image/png;base64,${data}`;
    await img.decode();
    const canvas = Object.assign(document.createElement('canvas'), { width: img.width, height: img.height });
    const ctx = canvas.getContext('2d');
    ctx.drawImage(img, 0, 0);
    const px = ctx.getImageData(0, 0, img.width, img.height).data;
    let drawn = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 0x15) + Math.abs(px[i + 1] - 0x19) + Math.abs(px[i + 2] - 0x1e) > 30) drawn++;
    }
    return drawn / (px.length / 4);
  }, png);
}

async function enterKey(page, key) {
  await page.locator('#key-form input').fill(key);
  await page.locator('#key-form button[type=submit]').click();
}

// --- viewer --------------------------------------------------------------------------------------

const rendered = (page, prefix) =>
  page.evaluate((p) => {
    const { map } = window.csrViewer;
    const layers = map.getStyle().layers.map((l) => l.id).filter((id) => id.startsWith(p));
    const ids = map.queryRenderedFeatures({ layers }).map((f) => `${f.layer.id.slice(p.length)}:${f.properties.id ?? f.properties.trip}`);
    return [...new Set(ids)].sort();
  }, prefix);

const idle = (page) =>
  page.waitForFunction(() => {
    const { map } = window.csrViewer;
    return map.loaded() && map.areTilesLoaded() && !map.isMoving();
  }, null, { timeout: 30000 });

async function setSlider(page, index) {
  await page.evaluate((i) => {
    const slider = document.getElementById('version-slider');
    slider.value = String(i);
    slider.dispatchEvent(new Event('input'));
  }, index);
  await page.waitForFunction((i) => document.getElementById('version-label').textContent.startsWith(`v${i + 1} `), index);
  await page.waitForTimeout(300);
  await idle(page);
}

/** Screen point of a lon/lat on the map (for clicks). */
const project = (page, lngLat) =>
  page.evaluate((ll) => {
    const { map } = window.csrViewer;
    const rect = map.getCanvas().getBoundingClientRect();
    const p = map.project(ll);
    return { x: rect.left + p.x, y: rect.top + p.y };
  }, lngLat);

/** A screen point on some drawn line of the shown version, nearest the map's centre (where to click). */
const someElement = (page) =>
  page.evaluate(() => {
    const { map } = window.csrViewer;
    const layers = map.getStyle().layers.map((l) => l.id).filter((id) => /^version-(?!flags)/.test(id) && map.getLayer(id).type === 'line');
    const f = map.queryRenderedFeatures({ layers })[0];
    const coords = f.geometry.type === 'LineString' ? f.geometry.coordinates : f.geometry.coordinates[0];
    const centre = map.project(map.getCenter());
    let best = null;
    for (let i = 1; i < coords.length; i++) {
      const [a, b] = [map.project(coords[i - 1]), map.project(coords[i])];
      for (let k = 0; k <= 50; k++) {
        const p = { x: a.x + ((b.x - a.x) * k) / 50, y: a.y + ((b.y - a.y) * k) / 50 };
        const d = Math.hypot(p.x - centre.x, p.y - centre.y);
        if (!best || d < best.d) best = { ...p, d };
      }
    }
    return map.unproject([best.x, best.y]).toArray();
  });

async function viewer(page) {
  const { tile, centre } = config;
  await page.goto(`${config.base}/viewer/#18/${centre[1]}/${centre[0]}`);
  check('key_form_shown', await page.locator('#key-form').isVisible());
  await enterKey(page, config.key);
  await page.waitForSelector('body[data-ready=true]');
  await page.waitForFunction(() => window.csrViewer.map.getSource('live') !== undefined);
  await idle(page);
  check('map_version_label', await page.locator('#map-version').textContent());
  check('live_rendered', await rendered(page, 'live-road-'));
  check('live_drawn_share', await drawnShare(page));
  await shot(page, 'viewer-live');

  // select the tile: a click on the map (away from elements)
  const offset = config.tile_offset || [0, -0.0005];
  const empty = await project(page, centre.map((v, i) => v + offset[i]));
  await page.mouse.click(empty.x, empty.y);
  await page.waitForSelector('#versions:not([hidden])');
  check('tile_name', await page.locator('#tile-name').textContent());
  await idle(page);
  const versions = [];
  const n = Number(await page.locator('#version-slider').getAttribute('max')) + 1;
  for (let i = n - 1; i >= 0; i--) {
    await setSlider(page, i);
    versions.push({
      index: i,
      label: await page.locator('#version-label').textContent(),
      drawn: await rendered(page, 'version-'),
      diff: await rendered(page, 'diff-'),
    });
    await shot(page, `viewer-version-${i + 1}`);
  }
  check('versions', versions);

  // at the newest version: the flagged road boundary; then click an element for its details
  await setSlider(page, n - 1);
  check('flagged', (await rendered(page, 'version-')).filter((id) => id.startsWith('flags:')));
  check('flag_styles', await flagStyles(page, 'version-flags'));
  check('legend', await page.locator('#legend').innerText());
  const target = await project(page, config.click_lnglat || (await someElement(page)));
  await page.mouse.click(target.x, target.y);
  await page.waitForSelector('#element-panel:not([hidden]) dl');
  await page.waitForFunction(() => document.querySelector('#element ol, #element p.muted'));
  check('element_text', await page.locator('#element').innerText());
  await shot(page, 'viewer-element');

  // trips in view: raw and aligned trajectories of the selected ones
  await page.locator('#live-button').click();
  await page.locator('#trips-refresh').click();
  await page.waitForSelector('#trips input[type=checkbox]');
  check('trips_listed', await page.locator('#trips input[type=checkbox]').count());
  for (const box of await page.locator('#trips input[type=checkbox]').all()) await box.check();
  await page.waitForFunction((n) => window.csrViewer.state.tracks.size === n, await page.locator('#trips input[type=checkbox]').count());
  await page.waitForTimeout(300);
  await idle(page);
  check('tracks_rendered', await rendered(page, 'track-'));
  await shot(page, 'viewer-trips');

  // corrections (admin): list the tile's match pairs, reject one, see a new version (and undo it)
  await correction(page, Boolean(config.correct));
}

/** The flag layer's paint as MapLibre evaluated it for each drawn feature: id -> its flags and style. */
const flagStyles = (page, layer) =>
  page.evaluate((id) => {
    const { map } = window.csrViewer;
    const out = {};
    for (const f of map.queryRenderedFeatures({ layers: [id] })) {
      const p = f.layer.paint;
      const c = p['line-color'];
      out[f.properties.id] = {
        flags: String(f.properties.flags), width: p['line-width'], opacity: p['line-opacity'], blur: p['line-blur'],
        color: typeof c === 'string' ? c : [c.r, c.g, c.b, c.a].map((v) => Math.round(v * 255)).join(','),
      };
    }
    return out;
  }, layer);

// --- opening: where the viewer opens, by the URL's hash ------------------------------------------

/** Open ``/viewer/`` with each of ``config.hashes`` (a fresh page load each): where the map opened
 * (on the linked view or fitted to the data), its view, and the live features rendered in it. */
async function open(page) {
  const seen = [];
  for (const [i, hash] of config.hashes.entries()) {
    await page.goto('about:blank');
    await page.goto(`${config.base}/viewer/${hash}`);
    if (i === 0) await enterKey(page, config.key);
    await page.waitForSelector('body[data-ready=true]');
    await page.waitForFunction(() => window.csrViewer.map.getSource('live') !== undefined);
    await page.waitForTimeout(300);
    await idle(page);
    seen.push(await page.evaluate((h) => {
      const { map, state } = window.csrViewer;
      const layers = state.liveLayers.filter((id) => map.getLayer(id));
      const b = map.getBounds();
      return {
        hash: h, opened_on: state.openedOn, zoom: map.getZoom(), hash_after: location.hash,
        view: [b.getWest(), b.getSouth(), b.getEast(), b.getNorth()],
        rendered: new Set(map.queryRenderedFeatures({ layers }).map((f) => f.properties.id)).size,
      };
    }, hash));
    seen[seen.length - 1].drawn_share = await drawnShare(page);
    await shot(page, `open-${i}`);
  }
  check('opened', seen);
}

async function correction(page, act) {
  // the tile panel loaded the pairs when the tile was selected: shown when the API lists them
  const visible = await page.locator('#corrections').isVisible();
  check('corrections_visible', visible);
  if (!visible || !act) return;
  check('pairs_listed', await page.locator('#pairs tr[data-pair]').count());
  const versionsBefore = Number(await page.locator('#version-slider').getAttribute('max')) + 1;
  await shot(page, 'viewer-corrections');
  const reject = page.locator('#pairs tr[data-pair] button.danger').first();
  if (!(await reject.count())) return;
  const pairId = await page.locator('#pairs tr[data-pair]').first().getAttribute('data-pair');
  check('rejected_pair', pairId);
  const finished = (what) =>
    page.waitForFunction((w) => new RegExp(`^${w}: (job done|job failed|still running)`).test(document.getElementById('tile-message').textContent), what, { timeout: 180000 });
  await reject.click();
  await finished('reject_pair');
  check('correction_message', await page.locator('#tile-message').textContent());
  check('corrections_listed', await page.locator('#correction-list tr[data-correction]').count());
  check('pair_status_after', await page.locator(`#pairs tr[data-pair="${pairId}"] td:nth-child(4)`).textContent().catch(() => null));
  const versionsAfter = Number(await page.locator('#version-slider').getAttribute('max')) + 1;
  check('versions_after_correction', versionsAfter - versionsBefore);
  check('correction_row', await page.locator('#correction-list tr[data-correction]').first().innerText());
  await shot(page, 'viewer-after-correction');
  // undo it: another version
  await page.locator('#correction-list tr[data-correction] button', { hasText: 'undo' }).first().click();
  await finished('undo');
  check('undo_message', await page.locator('#tile-message').textContent());
  check('versions_after_undo', Number(await page.locator('#version-slider').getAttribute('max')) + 1 - versionsAfter);
  check('correction_row_after_undo', await page.locator('#correction-list tr[data-correction]').first().innerText());
  await shot(page, 'viewer-after-undo');
  if (config.add_offset) await addPair(page, finished);
}

/** Add a pair through the form: prefilled by a click on a listed (active) pair, with an offset. */
async function addPair(page, finished) {
  const row = page.locator('#pairs tr[data-pair]', { has: page.locator('td:nth-child(4)', { hasText: /^active$/ }) }).first();
  const pairId = await row.getAttribute('data-pair');
  await row.locator('td').first().click();
  const form = page.locator('#add-pair');
  const formValues = () => form.evaluate((f) => ({
    trip_i: f.elements.trip_i.value, trip_j: f.elements.trip_j.value || null,
    frames_i: [...f.querySelectorAll('[name=frames_i]')].map((i) => Number(i.value)),
    frames_j: [...f.querySelectorAll('[name=frames_j]')].map((i) => Number(i.value)),
  }));
  const prefilled = await formValues();
  const pair = await page.evaluate((id) => window.csrViewer.state.pairs.find((p) => p.id === id), pairId);
  check('add_prefilled', prefilled);
  check('add_from_pair', { id: pairId, trip_i: pair.trip_i, trip_j: pair.trip_j, frames_i: pair.frames_i, frames_j: pair.frames_j });
  check('add_trip_options', await form.locator('select[name=trip_j] option').count());
  // a frame beyond the trip: the API's 422 names the field, the form shows it
  const last = form.locator('[name=frames_i]').nth(1);
  await last.fill('999999');
  await form.locator('button[type=submit]').click();
  await page.waitForSelector('#add-pair-message.error');
  check('add_error_message', await page.locator('#add-pair-message').textContent());
  check('add_error_marked', await form.locator('[name=frames_i].invalid').count());
  await shot(page, 'viewer-add-pair-error');
  await last.fill(String(prefilled.frames_i[1]));
  const inputs = form.locator('[name=offset_xyyaw]');
  for (const [k, v] of config.add_offset.entries()) await inputs.nth(k).fill(String(v));
  await form.locator('[name=note]').fill('browser test: pair added by hand');
  await form.locator('button[type=submit]').click();
  await page.waitForFunction(() => /^correction \S+ queued: job \S+/.test(document.getElementById('add-pair-message').textContent));
  check('add_answer_message', await page.locator('#add-pair-message').textContent());
  await finished('add_pair');
  check('add_message', await page.locator('#tile-message').textContent());
  check('add_version_label', await page.locator('#version-label').textContent());
  check('add_correction_rows', await page.locator('#correction-list tr[data-correction]').allInnerTexts());
  check('add_pair_rows', await page.locator('#pairs tr[data-pair]').evaluateAll((rows) => rows.map((r) => ({
    id: r.dataset.pair, trips: r.children[0].title, status: r.children[3].textContent,
  }))));
  await page.locator('#pairs tr[data-pair] .human').first().evaluate((e) => e.closest('tr').scrollIntoView({ block: 'start' }));
  await shot(page, 'viewer-after-add-pair');
}

// --- held-back lines ------------------------------------------------------------------------------

/** The held-back lines drawn: unique feature ids on the ``held-back`` layer, and the FeatureCollection's size. */
const heldBackDrawn = (page) =>
  page.evaluate(() => {
    const { map, state } = window.csrViewer;
    const ids = map.queryRenderedFeatures({ layers: ['held-back'] }).map((f) => f.properties.id);
    return { rendered: [...new Set(ids)].sort(), source: state.heldBack ? state.heldBack.features.length : null };
  });

/** Wait for the toggle's answer about ``tile``: its response, then the text it leads to. */
async function heldBackAnswer(page, tile, act) {
  const answered = page.waitForResponse((r) => r.url().includes(`/v1/tiles/${tile}/held-back`));
  await act();
  const response = await answered;
  await page.waitForFunction(() => document.getElementById('held-back-count').textContent !== 'loading…');
  await page.waitForTimeout(300);
  await idle(page);
  const url = new URL(response.url());
  return {
    path: url.pathname + url.search, status: response.status(),
    text: await page.locator('#held-back-count').textContent(), ...(await heldBackDrawn(page)),
  };
}

/** The "held-back lines" toggle of the tile panel, over ``config.tiles`` ({name, click: [lon, lat]}),
 * visited in order: off at first, then on; the slider's version and the live map's latest; a
 * held-back line's details; off again at the end. */
async function heldBack(page) {
  const [first] = config.tiles;
  await page.goto(`${config.base}/viewer/#18/${first.click[1]}/${first.click[0]}`);
  await enterKey(page, config.key);
  await page.waitForSelector('body[data-ready=true]');
  await page.waitForFunction(() => window.csrViewer.map.getSource('live') !== undefined);
  await idle(page);
  const tiles = {};
  for (const [i, tile] of config.tiles.entries()) {
    await page.evaluate((ll) => window.csrViewer.map.jumpTo({ center: ll, zoom: 18 }), tile.click);
    await idle(page);
    const point = await project(page, tile.click);
    const seen = {};
    const click = () => page.mouse.click(point.x, point.y);
    if (i === 0) {
      await click();
      await page.waitForSelector('#versions:not([hidden])');
      await page.waitForFunction((name) => document.getElementById('tile-name').textContent === name, tile.name);
      await idle(page);
      seen.off = { text: await page.locator('#held-back-count').textContent(), ...(await heldBackDrawn(page)) };
      // on: the version the slider shows (the newest when a tile is selected)
      seen.on = await heldBackAnswer(page, tile.name, () => page.locator('#held-back-toggle').check());
    } else {
      seen.on = await heldBackAnswer(page, tile.name, click); // the toggle stays on from tile to tile
    }
    seen.tile_name = await page.locator('#tile-name').textContent();
    seen.version_label = await page.locator('#version-label').textContent();
    seen.text_class = await page.locator('#held-back-count').getAttribute('class');
    await shot(page, `held-back-${tile.name.replaceAll('/', '-')}`);
    if (seen.on.rendered.length) {
      // a held-back line's details: a click on the middle of its geometry
      const middle = await page.evaluate(() => {
        const coords = window.csrViewer.state.heldBack.features[0].geometry.coordinates;
        return { id: window.csrViewer.state.heldBack.features[0].properties.id, at: coords[Math.floor(coords.length / 2)] };
      });
      const target = await project(page, middle.at);
      await page.mouse.click(target.x, target.y);
      await page.waitForFunction((id) => document.querySelector('#element-panel:not([hidden]) dl')?.innerText.includes(id), middle.id);
      await page.waitForFunction(() => document.querySelector('#element ol, #element p.muted'));
      seen.clicked_id = middle.id;
      seen.element_text = await page.locator('#element').innerText();
      await shot(page, 'held-back-element');
      // the live map: the tile's latest version (no ?version)
      seen.live = await heldBackAnswer(page, tile.name, () => page.locator('#live-button').click());
    }
    tiles[tile.name] = seen;
  }
  await page.locator('#held-back-toggle').uncheck();
  await page.waitForTimeout(300);
  await idle(page);
  check('tiles', tiles);
  check('off_again', { text: await page.locator('#held-back-count').textContent(), ...(await heldBackDrawn(page)) });
}

// --- ops -----------------------------------------------------------------------------------------

async function ops(page) {
  await page.goto(`${config.base}/ops/`);
  await enterKey(page, config.key);
  await page.waitForSelector('#jobs tbody tr');
  await page.waitForSelector('#dirty tbody tr').catch(() => null);
  const row = page.locator(`#jobs tr[data-job="${config.retry_job}"]`);
  await row.waitFor();
  check('summary_failed', await page.locator('.card.failed .n').textContent());
  check('failed_row', await row.innerText());
  check('dirty_rows', await page.locator('#dirty tbody tr').count());
  check('queue_ingest', await page.locator('#queues tr[data-queue=ingest]').innerText());
  // the charts: the queue depth sampled at each refresh (at least two samples), the jobs' durations
  await page.waitForFunction(() => Number(document.querySelector('#depth-chart g[data-series=queued]')?.dataset.samples) >= 2, null, { timeout: 30000 });
  check('charts', await page.evaluate(() => Object.fromEntries(['depth-chart', 'duration-chart'].map((id) => [id,
    Object.fromEntries([...document.querySelectorAll(`#${id} g[data-series]`)].map((g) => [g.dataset.series, {
      samples: Number(g.dataset.samples), circles: g.querySelectorAll('circle').length,
      polyline: g.querySelector('polyline')?.getAttribute('points').split(' ').length ?? 0,
    }]))]))));
  await shot(page, 'ops-failed');
  await row.locator('button', { hasText: 'retry' }).click();
  await page.waitForFunction(() => /retrying/.test(document.getElementById('ops-message').textContent));
  check('message', await page.locator('#ops-message').textContent());
  // the new job appears and runs to its end (the page refreshes itself)
  await page.waitForFunction((id) => {
    const old = document.querySelector(`#jobs tr[data-job="${id}"]`);
    const rows = [...document.querySelectorAll('#jobs tbody tr')];
    const newest = rows.find((r) => r.children[2].textContent === old?.children[2].textContent && r !== old);
    return old && /retried/.test(old.innerText) && newest && ['done', 'failed'].includes(newest.dataset.state);
  }, config.retry_job, { timeout: 60000 });
  check('rows_for_subject', await page.evaluate((id) => {
    const subject = document.querySelector(`#jobs tr[data-job="${id}"]`).children[2].textContent;
    return [...document.querySelectorAll('#jobs tbody tr')].filter((r) => r.children[2].textContent === subject)
      .map((r) => ({ id: r.dataset.job, state: r.dataset.state, text: r.innerText }));
  }, config.retry_job));
  await shot(page, 'ops-retried');
}

// --- main ----------------------------------------------------------------------------------------

const browser = await chromium.launch({ executablePath: config.chromium || '/usr/bin/chromium', args: CHROMIUM_ARGS, headless: true });
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on('console', (m) => m.type() !== 'debug' && result.console.push(`${m.type()}: ${m.text()}`));
  page.on('pageerror', (e) => result.errors.push(String(e)));
  await { viewer, open, 'held-back': heldBack, ops }[scenario](page);
} catch (err) {
  result.errors.push(String(err.stack || err));
  try {
    const pages = browser.contexts().flatMap((c) => c.pages());
    if (pages.length) await shot(pages[0], `${scenario}-failure`);
  } catch {
    /* the failure screenshot is best effort */
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));

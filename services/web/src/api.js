// The API key (kept in localStorage, sent as Bearer) and a small fetch helper shared by both pages.

const KEY_STORAGE = 'csr.apiKey';

export const apiKey = () => localStorage.getItem(KEY_STORAGE) || '';

export class ApiError extends Error {
  constructor(status, body) {
    super(body?.message || `HTTP ${status}`);
    this.status = status;
    this.body = body;
  }
}

/** fetch an API path with the key; JSON in and out. Throws ApiError for a non-2xx answer.
 * ``fresh``: revalidate a cached answer (the TileJSON is cacheable for a short while). */
export async function api(path, { method = 'GET', body, fresh = false } = {}) {
  const headers = { Authorization: `Bearer ${apiKey()}` };
  if (body !== undefined) headers['Content-Type'] = 'application/json';
  const init = { method, headers, body: body === undefined ? undefined : JSON.stringify(body) };
  if (fresh) init.cache = 'no-cache'; // revalidate what the API lets browsers cache for a while
  const res = await fetch(path, init);
  const text = await res.text();
  let data = null;
  try {
    data = text ? JSON.parse(text) : null;
  } catch {
    data = { message: text };
  }
  if (!res.ok) {
    if (res.status === 401) showKeyForm('The key was refused: enter another.');
    throw new ApiError(res.status, data);
  }
  return data;
}

/** The key form in the header: shown until a key is saved; `onSaved` runs after a save. */
export function setupKeyForm(onSaved) {
  const form = document.getElementById('key-form');
  const input = form.querySelector('input');
  form.addEventListener('submit', (event) => {
    event.preventDefault();
    localStorage.setItem(KEY_STORAGE, input.value.trim());
    input.value = '';
    form.hidden = true;
    document.getElementById('key-status').textContent = 'key set';
    onSaved();
  });
  document.getElementById('key-change').addEventListener('click', () => showKeyForm(''));
  if (!apiKey()) showKeyForm('Enter an API key (reader or admin).');
  else document.getElementById('key-status').textContent = 'key set';
  return Boolean(apiKey());
}

function showKeyForm(message) {
  const form = document.getElementById('key-form');
  form.hidden = false;
  form.querySelector('.hint').textContent = message;
  form.querySelector('input').focus();
}

/** Tiny DOM helper: el('td', {class: 'x'}, 'text', childNode) */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k.startsWith('on')) node.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) node.setAttribute(k, v === true ? '' : v);
  }
  node.append(...children.filter((c) => c !== undefined && c !== null).map((c) => (c instanceof Node ? c : String(c))));
  return node;
}

export const fmt = (v, digits = 2) => (typeof v === 'number' ? v.toFixed(digits) : v ?? '—');

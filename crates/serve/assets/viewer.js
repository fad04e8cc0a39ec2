// crossview live viewer: the latest frame's boxes per camera, coloured by track id.
//
// Data: GET /v1/scenes, GET /v1/scenes/{scene}, and the Server-Sent Events of
// GET /v1/scenes/{scene}/events?boxes=true, read with fetch() + a ReadableStream so that the
// API key travels in an Authorization header (EventSource cannot send one), never in a URL.
// The key is asked for only when the server answers 401 and is kept in sessionStorage.
//
// For tests and scripts the page mirrors what it did in data-* attributes: <body data-state>
// (loading | need-token | connecting | live | error), #status[data-frames] (frame events
// received), and per camera panel data-frames (frames drawn), data-last-frame,
// data-boxes-drawn, data-matched (boxes in a multi-camera identity), data-unmatched, and
// data-clock / data-clock-offset (the server's live clock estimate, polled every 5 s) and
// data-fit (whether the camera still fits the model: the same poll).
'use strict';

(() => {
  const TOKEN_KEY = 'crossview.apiKey';
  const RATE_WINDOW_MS = 5000;
  const CLOCK_POLL_MS = 5000;
  const RETRY_MS = [500, 1000, 2000, 5000];
  const MAX_CANVAS_SIDE = 1280;
  const MAX_BUFFER_CHARS = 64 << 20;
  const GREY = '#8a9099';
  const BACKGROUND = '#15181c';

  const $ = (id) => document.getElementById(id);
  const view = {
    scene: null,
    panels: [],
    controller: null,
    generation: 0,
    frames: 0,
    arrivals: [],
    retry: 0,
    retryTimer: null,
  };

  class AuthError extends Error {}

  function token() {
    try {
      return sessionStorage.getItem(TOKEN_KEY) || '';
    } catch (_) {
      return '';
    }
  }

  function setToken(value) {
    try {
      if (value) sessionStorage.setItem(TOKEN_KEY, value);
      else sessionStorage.removeItem(TOKEN_KEY);
    } catch (_) {
      // Storage disabled: the key lives as long as the page.
    }
  }

  function setState(state, text) {
    document.body.dataset.state = state;
    $('conn').textContent = text;
    $('conn').className = 'conn ' + state;
  }

  async function api(path, init = {}) {
    const headers = Object.assign({}, init.headers || {});
    const t = token();
    if (t) headers.Authorization = 'Bearer ' + t;
    const r = await fetch(path, Object.assign({}, init, {
      headers,
      cache: 'no-store',
      credentials: 'omit',
      referrerPolicy: 'no-referrer',
    }));
    if (r.status === 401) throw new AuthError('the server refused the API key');
    if (!r.ok) throw new Error(path + ': HTTP ' + r.status);
    return r;
  }

  // ---- connection lifecycle ---------------------------------------------------------------

  function stopStream() {
    view.generation += 1;
    if (view.controller) view.controller.abort();
    view.controller = null;
    if (view.retryTimer) clearTimeout(view.retryTimer);
    view.retryTimer = null;
  }

  function retryLater(what) {
    const delay = RETRY_MS[Math.min(view.retry, RETRY_MS.length - 1)];
    view.retry += 1;
    setState('error', what + ' — retrying in ' + (delay / 1000) + ' s');
    view.retryTimer = setTimeout(start, delay);
  }

  function askToken(message) {
    stopStream();
    view.scene = null;
    view.panels = [];
    $('panels').replaceChildren();
    $('status').hidden = true;
    $('scene').replaceChildren();
    $('scene').disabled = true;
    $('forget').hidden = !token();
    $('token-form').hidden = false;
    $('token-error').hidden = !message;
    $('token-error').textContent = message || '';
    setState('need-token', 'API key needed');
    $('token').focus();
  }

  async function start() {
    stopStream();
    $('token-form').hidden = true;
    setState('loading', 'loading scenes…');
    let scenes;
    try {
      const body = await (await api('/v1/scenes')).json();
      scenes = Array.isArray(body.scenes) ? body.scenes : [];
    } catch (e) {
      if (e instanceof AuthError) askToken(token() ? 'That key was refused.' : '');
      else retryLater('cannot list scenes (' + e.message + ')');
      return;
    }
    $('forget').hidden = !token();
    const select = $('scene');
    select.replaceChildren(...scenes.map((s) => {
      const o = document.createElement('option');
      o.value = o.textContent = String(s.name);
      return o;
    }));
    select.disabled = scenes.length === 0;
    if (scenes.length === 0) {
      setState('error', 'the server serves no scene');
      return;
    }
    const wanted = new URLSearchParams(location.hash.slice(1)).get('scene');
    const chosen = scenes.find((s) => s.name === wanted) || scenes[0];
    select.value = chosen.name;
    openScene(chosen);
  }

  function openScene(info) {
    stopStream();
    view.scene = info;
    view.frames = 0;
    view.arrivals = [];
    $('status').dataset.frames = '0';
    $('frames').textContent = '0';
    $('status').hidden = false;
    $('scene-info').textContent = sceneText(info);
    const cams = Array.isArray(info.cameras) ? info.cameras : [];
    view.panels = cams.map((cam, c) => makePanel(cam, c));
    // A near-square grid: 4 cameras in 2 × 2, 6 in 3 × 2 (CSSOM, allowed by the CSP).
    const cols = Math.max(1, Math.ceil(Math.sqrt(cams.length)));
    $('panels').style.setProperty('--cols', String(cols));
    $('panels').style.setProperty('--rows', String(Math.max(1, Math.ceil(cams.length / cols))));
    $('panels').replaceChildren(...view.panels.map((p) => p.el));
    showClock(info);
    showRetrain(info);
    connect(view.generation);
  }

  function sceneText(info) {
    const parts = [String(info.name), (info.cameras || []).length + ' cameras'];
    if (Number.isFinite(info.sync_timeout_ms)) parts.push('sync timeout ' + info.sync_timeout_ms + ' ms');
    if (Number.isFinite(info.threshold)) parts.push('threshold ' + info.threshold.toFixed(3));
    if (info.model_version) parts.push('model ' + info.model_version);
    return parts.join(' · ');
  }

  async function connect(generation) {
    const controller = new AbortController();
    view.controller = controller;
    const name = view.scene.name;
    setState('connecting', 'connecting…');
    let response;
    try {
      response = await api('/v1/scenes/' + encodeURIComponent(name) + '/events?boxes=true', {
        signal: controller.signal,
        headers: { Accept: 'text/event-stream' },
      });
    } catch (e) {
      if (generation !== view.generation) return;
      if (e instanceof AuthError) askToken('That key was refused.');
      else retryLater('cannot subscribe (' + e.message + ')');
      return;
    }
    if (generation !== view.generation) return;
    view.retry = 0;
    setState('live', 'live');
    try {
      await readEvents(response.body, generation);
    } catch (e) {
      if (generation !== view.generation) return;
    }
    if (generation === view.generation) retryLater('the event stream ended');
  }

  // ---- Server-Sent Events over fetch ------------------------------------------------------

  async function readEvents(body, generation) {
    const reader = body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = '';
    for (;;) {
      const { value, done } = await reader.read();
      if (done || generation !== view.generation) return;
      buffer += value;
      // Normalise line ends once a block is complete (a CR may end a chunk).
      let latest = null;
      for (;;) {
        buffer = buffer.replace(/\r\n?/g, '\n');
        const cut = buffer.indexOf('\n\n');
        if (cut < 0) break;
        const ev = parseEvent(buffer.slice(0, cut));
        buffer = buffer.slice(cut + 2);
        if (ev.event === 'frame') {
          received();
          latest = ev.data;
        } else if (ev.event === 'error') {
          // {"error": {"kind", "message", "field"}}, as every HTTP error body.
          let message = ev.data;
          try { message = JSON.parse(ev.data).error.message || ev.data; } catch (_) { /* text */ }
          showError('server: ' + message);
        }
      }
      if (buffer.length > MAX_BUFFER_CHARS) throw new Error('event too large');
      // Draw only the newest frame of a chunk: the page shows "now", it does not replay.
      if (latest !== null) {
        let frame = null;
        try {
          frame = JSON.parse(latest);
        } catch (_) {
          showError('an event was not JSON');
        }
        if (frame && typeof frame === 'object') render(frame);
      }
    }
  }

  function parseEvent(block) {
    const ev = { event: 'message', data: '' };
    const data = [];
    for (const line of block.split('\n')) {
      if (line === '' || line.startsWith(':')) continue;
      const colon = line.indexOf(':');
      const field = colon < 0 ? line : line.slice(0, colon);
      let value = colon < 0 ? '' : line.slice(colon + 1);
      if (value.startsWith(' ')) value = value.slice(1);
      if (field === 'event') ev.event = value;
      else if (field === 'data') data.push(value);
    }
    ev.data = data.join('\n');
    return ev;
  }

  function received() {
    view.frames += 1;
    $('status').dataset.frames = String(view.frames);
    $('frames').textContent = String(view.frames);
    view.arrivals.push(performance.now());
    showRate();
  }

  function showRate() {
    const now = performance.now();
    while (view.arrivals.length && now - view.arrivals[0] > RATE_WINDOW_MS) view.arrivals.shift();
    const n = view.arrivals.length;
    let fps = 0;
    if (n >= 2) {
      const span = (now - view.arrivals[0]) / 1000;
      fps = span > 0 ? (n - 1) / span : 0;
    }
    $('rate').textContent = fps.toFixed(1) + ' frames/s (last ' + RATE_WINDOW_MS / 1000 + ' s)';
  }

  // ---- drawing ----------------------------------------------------------------------------

  function makePanel(cam, c) {
    const w = Math.max(1, Number(cam.width) || 1);
    const h = Math.max(1, Number(cam.height) || 1);
    const scale = Math.min(1, MAX_CANVAS_SIDE / Math.max(w, h));
    const el = document.createElement('figure');
    el.className = 'panel';
    el.dataset.camera = String(cam.name);
    el.dataset.frames = '0';
    el.dataset.boxesDrawn = '0';
    el.dataset.matched = '0';
    el.dataset.unmatched = '0';
    const canvas = document.createElement('canvas');
    canvas.width = Math.max(1, Math.round(w * scale));
    canvas.height = Math.max(1, Math.round(h * scale));
    const caption = document.createElement('figcaption');
    const title = document.createElement('strong');
    title.textContent = String(cam.name);
    const size = document.createElement('span');
    const declared = Number(cam.offset) || 0;
    size.textContent = w + '×' + h + (declared ? ' @' + (declared > 0 ? '+' : '') + declared : '');
    const clock = document.createElement('span');
    clock.className = 'clock';
    el.dataset.clock = 'none';
    const fit = document.createElement('span');
    fit.className = 'fit';
    el.dataset.fit = 'none';
    const counts = document.createElement('span');
    counts.className = 'counts';
    caption.append(title, size, clock, fit, counts);
    el.append(canvas, caption);
    const panel = { el, canvas, counts, clock, fit, index: c, w, h, scale };
    clearPanel(panel, 'waiting for frames');
    return panel;
  }

  function clearPanel(p, message) {
    const ctx = p.canvas.getContext('2d');
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = BACKGROUND;
    ctx.fillRect(0, 0, p.canvas.width, p.canvas.height);
    if (message) {
      ctx.fillStyle = GREY;
      ctx.font = Math.round(p.canvas.width / 30) + 'px sans-serif';
      ctx.textAlign = 'center';
      ctx.textBaseline = 'middle';
      ctx.fillText(message, p.canvas.width / 2, p.canvas.height / 2);
    }
    ctx.setTransform(p.scale, 0, 0, p.scale, 0, 0);
    return ctx;
  }

  // Screen pixels per image pixel of a panel (the canvas is letterboxed into its box).
  function displayScale(p) {
    const cw = p.canvas.clientWidth;
    const ch = p.canvas.clientHeight;
    const s = cw > 0 && ch > 0 ? Math.min(cw / p.w, ch / p.h) : p.scale;
    return s > 0 && Number.isFinite(s) ? s : 1;
  }

  // A stable, well-spread colour per track id (golden-angle hues).
  function colour(n) {
    const hue = (Number(n) * 137.508) % 360;
    return 'hsl(' + hue.toFixed(1) + ', 85%, 58%)';
  }

  function validBox(b) {
    return Array.isArray(b) && b.length === 4 && b.every(Number.isFinite) && b[2] > b[0] && b[3] > b[1];
  }

  function render(frame) {
    const identities = Array.isArray(frame.identities) ? frame.identities : [];
    const views = Array.isArray(frame.views) ? frame.views : [];
    const owners = view.panels.map(() => new Map());
    for (const id of identities) {
      for (const m of Array.isArray(id.members) ? id.members : []) {
        const owner = owners[m.camera_index];
        if (owner) owner.set(m.index, id);
      }
    }
    const boxesOf = new Map();
    for (const v of views) boxesOf.set(v.camera_index, Array.isArray(v.boxes) ? v.boxes : []);
    for (const p of view.panels) {
      const boxes = boxesOf.get(p.index);
      let drawn = 0;
      let matched = 0;
      if (boxes === undefined) {
        clearPanel(p, 'not reported in frame ' + frame.frame_id);
        p.el.classList.add('missing');
      } else {
        p.el.classList.remove('missing');
        const ctx = clearPanel(p, boxes.length ? '' : 'nobody in view');
        // Sizes in image pixels that come out as 2 px lines and 12 px labels on screen.
        const perPixel = displayScale(p);
        const line = 2 / perPixel;
        const font = Math.round(12 / perPixel);
        ctx.font = 'bold ' + font + 'px sans-serif';
        ctx.textAlign = 'left';
        ctx.textBaseline = 'bottom';
        boxes.forEach((b, i) => {
          if (!validBox(b)) return;
          const id = owners[p.index].get(i);
          const multi = id !== undefined && Array.isArray(id.members) && id.members.length > 1;
          const key = id === undefined ? null : (id.track_id !== undefined && id.track_id !== null ? id.track_id : id.id);
          const c = multi ? colour(key) : GREY;
          ctx.strokeStyle = c;
          ctx.lineWidth = line;
          ctx.setLineDash(id === undefined ? [line * 3, line * 2] : []);
          ctx.strokeRect(b[0], b[1], b[2] - b[0], b[3] - b[1]);
          drawn += 1;
          if (multi) matched += 1;
          if (key !== null) {
            const text = (id.track_id !== undefined && id.track_id !== null ? '' : '#') + key;
            const tw = ctx.measureText(text).width + font * 0.4;
            const y = Math.max(font * 1.2, b[1]);
            ctx.fillStyle = c;
            ctx.fillRect(b[0] - line / 2, y - font * 1.2, tw, font * 1.2);
            ctx.fillStyle = '#000';
            ctx.fillText(text, b[0] + font * 0.2, y - font * 0.1);
          }
        });
        ctx.setLineDash([]);
      }
      p.el.dataset.frames = String(Number(p.el.dataset.frames) + 1);
      p.el.dataset.lastFrame = String(frame.frame_id);
      p.el.dataset.boxesDrawn = String(drawn);
      p.el.dataset.matched = String(matched);
      p.el.dataset.unmatched = String(drawn - matched);
      p.counts.textContent = boxes === undefined ? 'missing' : drawn + ' boxes, ' + matched + ' matched';
    }
    const multi = identities.filter((i) => Array.isArray(i.members) && i.members.length > 1).length;
    $('frame-id').textContent = String(frame.frame_id);
    const missing = Array.isArray(frame.missing_cameras) ? frame.missing_cameras : [];
    $('frame-state').textContent = frame.complete ? 'complete' : 'partial (missing ' + missing.join(', ') + ')';
    $('frame-state').className = frame.complete ? '' : 'warn';
    $('latency').textContent = Number.isFinite(frame.latency_ms) ? frame.latency_ms.toFixed(1) + ' ms' : '–';
    $('identities').textContent = frame.status === 'no_model'
      ? 'not associated: the scene has no model yet'
      : identities.length + ' (' + multi + ' in several cameras)';
    $('model').textContent = frame.model_version || 'none yet';
    if (frame.error) showError('frame ' + frame.frame_id + ': ' + frame.error);
    else $('frame-error').hidden = true;
  }

  // ---- clock offsets ----------------------------------------------------------------------

  // Each camera's live clock offset (the scene description's `clock`), next to its name:
  // data-clock is 'none' (no estimate yet), 'unknown', 'in-sync' or 'off', data-clock-offset
  // the offset in frames.
  function showClock(info) {
    const cams = info && info.clock && Array.isArray(info.clock.cameras) ? info.clock.cameras : [];
    for (const p of view.panels) {
      const c = cams.find((x) => x && x.camera === p.el.dataset.camera);
      if (!c) continue;
      const f = c.offset_frames;
      if (typeof f !== 'number' || !Number.isFinite(f)) {
        p.el.dataset.clock = 'unknown';
        p.clock.textContent = 'clock: unknown';
        p.clock.title = 'no confident overlap with another camera, or nobody moved';
        continue;
      }
      const off = Math.abs(f) > 0.5;
      p.el.dataset.clock = off ? 'off' : 'in-sync';
      p.el.dataset.clockOffset = f.toFixed(2);
      p.clock.textContent = off ? 'clock ' + (f > 0 ? '+' : '') + f.toFixed(1) + ' frames' : 'clock in sync';
      p.clock.title = 'estimated from the last ' + info.clock.frames + ' frames, confidence ' +
        (Number(c.confidence) || 0).toFixed(2);
    }
  }

  // Whether each camera still fits the model (the scene description's `fit`): data-fit is
  // 'none' (no look yet) or the state (fits, drifting, does_not_fit, silent, unknown); the
  // badge shows only what needs a look.
  const FIT_TEXT = {
    fits: '',
    drifting: 'fit drifting',
    does_not_fit: 'moved? does not fit the model',
    silent: 'silent',
    unknown: '',
  };

  function showFit(info) {
    const cams = info && info.fit && Array.isArray(info.fit.cameras) ? info.fit.cameras : [];
    for (const p of view.panels) {
      const c = cams.find((x) => x && x.camera === p.el.dataset.camera);
      if (!c || !(c.state in FIT_TEXT)) continue;
      p.el.dataset.fit = c.state;
      p.fit.textContent = FIT_TEXT[c.state];
      p.fit.title = typeof c.score === 'number'
        ? 'fit score ' + c.score.toFixed(2) + ' (1: as when the model was loaded)'
        : c.state;
    }
  }

  // Healing (`serve --auto-retrain`, the scene description's `retrain`): data-retrain is the
  // state (idle, waiting, training, gating); the text says what is happening and how the
  // last retrain ended.
  const RETRAIN_TEXT = {
    idle: 'watching',
    waiting: 'recording the new view of ',
    training: 'retraining for ',
    gating: 'checking the retrained model for ',
  };

  function showRetrain(info) {
    const r = info && info.retrain;
    $('retrain-row').hidden = !r;
    if (!r || !(r.state in RETRAIN_TEXT)) return;
    const el = $('retrain');
    el.dataset.retrain = r.state;
    const cams = Array.isArray(r.cameras) ? r.cameras.join(', ') : '';
    let text = RETRAIN_TEXT[r.state] + (r.state === 'idle' ? '' : cams);
    if (r.last_outcome) text += ' · last: ' + r.last_outcome;
    el.textContent = text;
    el.title = (r.last_reason || '') + (r.last_model ? ' (' + r.last_model + ')' : '') +
      ' · ' + (r.swapped || 0) + ' of ' + (r.attempts || 0) + ' retrains swapped in';
  }

  async function pollClock() {
    if (!view.scene) return;
    const generation = view.generation;
    try {
      const info = await (await api('/v1/scenes/' + encodeURIComponent(view.scene.name))).json();
      if (generation === view.generation) {
        showClock(info);
        showFit(info);
        showRetrain(info);
      }
    } catch (e) {
      // The event stream reports connection and key problems; a missed poll is retried.
    }
  }

  function showError(text) {
    $('frame-error').textContent = text;
    $('frame-error').hidden = false;
  }

  // ---- controls ---------------------------------------------------------------------------

  function init() {
    $('token-form').addEventListener('submit', (e) => {
      e.preventDefault();
      const value = $('token').value.trim();
      $('token').value = '';
      if (!value) return;
      setToken(value);
      start();
    });
    $('forget').addEventListener('click', () => {
      setToken('');
      start();
    });
    $('scene').addEventListener('change', async () => {
      const name = $('scene').value;
      history.replaceState(null, '', '#scene=' + encodeURIComponent(name));
      try {
        openScene(await (await api('/v1/scenes/' + encodeURIComponent(name))).json());
      } catch (e) {
        if (e instanceof AuthError) askToken('That key was refused.');
        else retryLater('cannot load scene ' + name + ' (' + e.message + ')');
      }
    });
    setInterval(showRate, 1000);
    setInterval(pollClock, CLOCK_POLL_MS);
    start();
  }

  if (document.readyState === 'loading') document.addEventListener('DOMContentLoaded', init);
  else init();
})();

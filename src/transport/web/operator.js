'use strict';
// factord web UI for operators, on `window.factord`: the login form (a token exchanged for an
// HttpOnly cookie, which EventSource sends too), the health panel, the session's history
// (timeline, event log refilled on load, rejected inputs, last_error), exports and ellipses.
(() => {
  const F = window.factord;
  const { $, api, el, num, getJSON, fmtInt, setStatus } = F;

  // ---------------------------------------------------------------- login
  // Shown when the API answers 401: with tokens in force a page has no other way to send one.
  // Whether this browser logged in (the cookie itself is HttpOnly): `log out` is shown only
  // then, never before a login nor on a server without tokens.
  const LOGGED_IN = 'factord.loggedIn';
  const remember = (yes) => { try { if (yes) localStorage.setItem(LOGGED_IN, '1'); else localStorage.removeItem(LOGGED_IN); } catch (_) { /* storage off */ } };
  const remembered = () => { try { return localStorage.getItem(LOGGED_IN) === '1'; } catch (_) { return false; } };
  F.showLogin = () => {
    remember(false);
    const logoutButton = $('logout');
    if (logoutButton) logoutButton.hidden = true;
    const box = $('login');
    if (!box.hidden) return;
    box.hidden = false;
    document.body.dataset.loginShown = 'true';
    const form = $('login-form'), input = $('login-token'), status = $('login-status');
    input.focus();
    form.addEventListener('submit', async (e) => {
      e.preventDefault();
      setStatus(status, 'checking…');
      try {
        const res = await fetch('/v1/login', {
          method: 'POST', headers: { 'Content-Type': 'application/json' },
          // The server takes the token exactly; tokens never hold whitespace, a paste may.
          body: JSON.stringify({ token: input.value.trim() }),
        });
        const body = await res.json().catch(() => null);
        if (!res.ok) throw new Error((body && body.error && body.error.message) || res.statusText);
        remember(!body || body.auth !== false);
        location.reload();
      } catch (err) {
        setStatus(status, `login failed: ${err.message}`, true);
      }
    });
  };
  const logout = $('logout');
  if (logout) {
    logout.hidden = !remembered();
    logout.addEventListener('click', async () => { await fetch('/v1/logout', { method: 'POST' }); remember(false); location.reload(); });
  }

  // ---------------------------------------------------------------- health (index page)
  F.startHealth = () => {
    const panel = $('health');
    const upFor = (s) => (s < 120 ? `${Math.round(s)} s` : s < 7200 ? `${Math.round(s / 60)} min` : `${(s / 3600).toFixed(1)} h`);
    async function refresh() {
      try {
        const h = await getJSON('/v1/health');
        const item = (label, value) => el('span', {}, label + ' ', el('b', { textContent: value }));
        panel.replaceChildren(el('span', { className: 'status ' + (h.status === 'ok' ? 'converged' : 'error'), textContent: h.status }),
          item('version', h.version), item('workers busy', `${fmtInt(h.busy_workers)} / ${fmtInt(h.workers)}`),
          item('queued', fmtInt(h.queued)), item('sessions', fmtInt(h.sessions)),
          item('up', num(h.uptime_seconds) ? upFor(h.uptime_seconds) : '—'));
        document.body.dataset.healthStatus = h.status;
      } catch (e) {
        panel.replaceChildren(el('span', { className: 'status error', textContent: `health unavailable: ${e.message}` }));
        document.body.dataset.healthStatus = 'unavailable';
      }
    }
    (async function loop() { await refresh(); setTimeout(loop, 5000); })();
  };

  F.describeError = (d) => {
    const e = d.error || {};
    return (num(d.sequence) ? `sequence ${d.sequence}: ` : '') + (d.producer ? `${d.producer}#${fmtInt(d.producer_seq)} ` : '') +
      (e.code ? `${e.code}: ` : '') + (e.field ? `[${e.field}] ` : '') + (e.message || d.raw || 'error');
  };

  // ---------------------------------------------------------------- history (session page)
  // On load the server's history refills the event log (through the live handlers) and the
  // timeline; after that the timeline, rejections and last_error are re-read after each solve.
  F.sessionHistory = (id, timeline, handlers) => {
    let busy = false, again = false, first = true, last = -Infinity; // last: when the last read started
    // At most one read every 2 s however fast the session solves (it carries the event log).
    async function refresh() {
      if (busy) { again = true; return; }
      const wait = last + 2000 - performance.now();
      if (wait > 0) { busy = true; setTimeout(() => { busy = false; refresh(); }, wait); return; }
      busy = true;
      last = performance.now();
      try {
        const h = await getJSON(api(id, '/history'));
        timeline.setPoints(h.timeline || []);
        if (first) {
          first = false;
          for (const e of h.events || []) if (handlers[e.event]) handlers[e.event](e.data, e.unix_ms);
        }
        const lastError = $('last-error');
        lastError.textContent = h.last_error ? `last error: ${h.last_error}` : 'no error';
        lastError.className = h.last_error ? 'statusline error' : 'statusline';
        const rows = (h.rejected || []).slice().reverse().map((e) =>
          el('li', { className: 'errors' }, el('time', { textContent: new Date(e.unix_ms).toLocaleTimeString() }), F.describeError(e.data)));
        $('rejected').replaceChildren(...(rows.length ? rows : [el('li', { className: 'muted', textContent: 'nothing rejected' })]));
        document.body.dataset.rejected = String(rows.length);
        document.body.dataset.historyLoaded = 'true';
      } catch (e) {
        $('last-error').textContent = `history unavailable: ${e.message}`;
      } finally {
        busy = false;
        if (again) { again = false; refresh(); }
      }
    }
    refresh();
    return { refresh };
  };

  // ---------------------------------------------------------------- exports and ellipses
  F.startOperator = (id, traj) => {
    for (const format of ['g2o', 'tum', 'ply']) {
      const a = $('export-' + format);
      a.href = api(id, '/estimate?format=' + format);
      a.download = `${id}.${format === 'tum' ? 'txt' : format}`;
    }
    const selected = new Set(), info = $('ellipse-info');
    async function load() {
      if (!selected.size) { traj.setEllipses(new Map()); info.textContent = 'click a pose for its covariance'; return; }
      try {
        const m = await getJSON(api(id, '/marginals?keys=' + [...selected].join(',')));
        traj.setEllipses(new Map(m.variables.filter((v) => !v.fixed && v.position_covariance).map((v) => [v.key, v.position_covariance])));
        info.textContent = `${selected.size} selected (95%, sequence ${fmtInt(m.sequence)})`;
      } catch (e) {
        info.textContent = `covariances unavailable: ${e.message}`;
      }
    }
    traj.onPick((key) => { if (!selected.delete(key)) selected.add(key); load(); });
    // A sample along the trajectory: every n-th pose, about ten.
    $('ellipse-sample').addEventListener('click', () => {
      const keys = traj.poses(), step = Math.max(1, Math.floor(keys.length / 10));
      selected.clear();
      for (let i = step - 1; i < keys.length; i += step) selected.add(keys[i]);
      load();
    });
    $('ellipse-clear').addEventListener('click', () => { selected.clear(); load(); });
  };
})();

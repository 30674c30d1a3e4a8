'use strict';
// factord web UI: shared helpers, then one start function per page (chosen by <body data-page>).
// No framework and no build step: the server embeds this file as it is.
(() => {
  const $ = (id) => document.getElementById(id);
  const api = (id, rest = '') => '/v1/sessions' + (id === undefined ? '' : '/' + encodeURIComponent(id) + rest);
  const num = (x) => typeof x === 'number' && Number.isFinite(x);
  const clock = () => new Date().toLocaleTimeString();

  function el(tag, props = {}, ...kids) {
    const e = Object.assign(document.createElement(tag), props);
    for (const k of kids) if (k != null) e.append(k);
    return e;
  }

  // Throws with the server's own message when it sent its {"error": {...}} body.
  async function getJSON(url) {
    const res = await fetch(url, { cache: 'no-store' });
    let body = null;
    try { body = await res.json(); } catch (_) { /* not JSON: the status line says enough */ }
    if (!res.ok) {
      const msg = body && body.error && body.error.message;
      throw Object.assign(new Error(`${res.status} ${msg || res.statusText}`), { status: res.status });
    }
    return body;
  }

  const fmtCost = (x) => (num(x) ? x.toPrecision(6) : '—');
  const fmtInt = (x) => (num(x) ? String(x) : '—');
  function fmtMs(seconds) {
    if (!num(seconds)) return '—';
    const ms = seconds * 1000;
    return (ms >= 100 ? Math.round(ms) : Number(ms.toPrecision(3))) + ' ms';
  }
  // The summary names have moved before; take whichever the server sends.
  function solveSeconds(summary) {
    if (!summary) return null;
    for (const k of ['solve_seconds', 'total_seconds', 'seconds']) if (num(summary[k])) return summary[k];
    return null;
  }
  function iterationLog(summary) {
    if (!summary) return [];
    if (Array.isArray(summary.iteration_log)) return summary.iteration_log;
    return Array.isArray(summary.iterations) ? summary.iterations : [];
  }
  // What the last incremental update did (Summary.used.incremental), like iSAM2's result.
  function incrementalItems(u, item) {
    if (!u) return [];
    return [item('relinearised', fmtInt(u.relinearized_variables)),
      item('refactored', `${fmtInt(u.refactored_columns)} / ${fmtInt(u.columns)} columns`),
      item('factor nnz', fmtInt(u.factor_nnz)),
      item('phases', `order ${fmtMs(u.order_seconds)}, factor ${fmtMs(u.factorize_seconds)}, solve ${fmtMs(u.solve_seconds)}`)];
  }
  function iterationCount(summary) {
    if (!summary) return null;
    return num(summary.iterations) ? summary.iterations : iterationLog(summary).length;
  }
  function statusOf(s) {
    if (s.solving) return ['solving', 'solving'];
    if (s.last_error) return ['error: ' + s.last_error, 'error'];
    if (!s.solves && !s.last_summary) return ['not solved yet', 'idle'];
    return s.converged ? ['converged', 'converged'] : ['not converged', 'not-converged'];
  }
  function statusEl(s) {
    const [text, cls] = statusOf(s);
    return el('span', { className: 'status ' + cls, textContent: text });
  }
  function setStatus(node, text, isError) {
    node.textContent = text;
    node.className = 'statusline' + (isError ? ' error' : '');
  }

  // Backing store = CSS size × devicePixelRatio, read on every draw so zoom and monitor moves stay sharp.
  function fitCanvas(canvas) {
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const bw = Math.max(1, Math.round(w * dpr)), bh = Math.max(1, Math.round(h * dpr));
    if (canvas.width !== bw || canvas.height !== bh) { canvas.width = bw; canvas.height = bh; }
    const ctx = canvas.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.font = '11px system-ui, -apple-system, "Segoe UI", Roboto, sans-serif';
    return { ctx, w, h };
  }
  function centredText(ctx, w, h, text) {
    ctx.fillStyle = '#66707c';
    ctx.textAlign = 'center';
    ctx.textBaseline = 'middle';
    ctx.font = '13px system-ui, sans-serif';
    ctx.fillText(text, w / 2, h / 2);
  }
  // Events can arrive far faster than frames; draw at most once per frame.
  function perFrame(draw) {
    let queued = false;
    return () => {
      if (queued) return;
      queued = true;
      requestAnimationFrame(() => { queued = false; draw(); });
    };
  }
  // Smallest 1, 2 or 5 × 10^k that is at least x.
  function niceStep(x) {
    const p = Math.pow(10, Math.floor(Math.log10(x)));
    const m = x / p;
    return (m <= 1 ? 1 : m <= 2 ? 2 : m <= 5 ? 5 : 10) * p;
  }
  function fmtLength(m) {
    const clean = (x) => Number(x.toPrecision(3));
    if (m >= 1000) return clean(m / 1000) + ' km';
    if (m >= 1) return clean(m) + ' m';
    if (m >= 0.01) return clean(m * 100) + ' cm';
    return clean(m * 1000) + ' mm';
  }
  const SUP = { '-': '⁻', 0: '⁰', 1: '¹', 2: '²', 3: '³', 4: '⁴', 5: '⁵', 6: '⁶', 7: '⁷', 8: '⁸', 9: '⁹' };
  const decade = (k) => (k === 0 ? '1' : k === 1 ? '10' : '10' + String(k).replace(/./g, (c) => SUP[c]));
  // A summary event as the log shows it: [class, text]. An incremental update (one pass of
  // relinearising what moved, `used.incremental`) is no solve that failed to converge: it says
  // so, in the neutral colour; green is a converged solve, amber one that stopped short.
  function describeSummary(solve, s) {
    const chi2 = `χ² ${fmtCost(s.initial_chi2)} → ${fmtCost(s.final_chi2)}`;
    if (s.used && s.used.incremental) {
      const passes = iterationCount(s);
      return ['update', `incremental update ${fmtInt(solve)}: ${chi2}, ${fmtInt(passes)} pass${passes === 1 ? '' : 'es'}, ${fmtMs(solveSeconds(s))}`];
    }
    const reason = s.termination && s.termination.reason ? `, ${s.termination.reason}` : '';
    return [s.converged ? 'summary' : 'not-converged', `solve ${fmtInt(solve)}: ${chi2}, ` +
      `${fmtInt(iterationCount(s))} iterations, ${fmtMs(solveSeconds(s))}, ${s.converged ? 'converged' : 'not converged'}${reason}`];
  }
  // Shared with plots.js and operator.js (loaded after this file, before the page starts).
  const F = window.factord = { $, api, num, clock, el, getJSON, fmtCost, fmtInt, fmtMs, solveSeconds, iterationLog,
    iterationCount, fitCanvas, perFrame, niceStep, decade, setStatus, describeSummary };

  // ---------------------------------------------------------------- index page
  function startIndex() {
    const tbody = $('sessions'), status = $('status');

    function row(info, res) {
      const s = res.status === 'fulfilled' ? res.value : null;
      const td = (text, cls = '') => el('td', { className: cls, textContent: text });
      const link = el('a', { href: '/sessions/' + encodeURIComponent(info.session), textContent: info.session });
      return el('tr', {},
        el('td', {}, link),
        td(info.kind || '—'),
        s ? el('td', {}, statusEl(s)) : td('stats unavailable', 'muted'),
        td(fmtInt(s && s.num_variables), 'num'),
        td(fmtInt(s && s.num_factors), 'num'),
        td(fmtCost(s && s.chi2), 'num'),
        td(fmtMs(solveSeconds(s && s.last_summary)), 'num'),
        td(fmtInt(s && s.solves), 'num'));
    }

    async function refresh() {
      try {
        const list = (await getJSON(api())).sessions || [];
        const stats = await Promise.allSettled(list.map((s) => getJSON(api(s.session))));
        tbody.replaceChildren(...list.map((info, i) => row(info, stats[i])));
        if (!list.length) tbody.append(el('tr', {}, el('td', { colSpan: 8, className: 'empty', textContent: 'no sessions yet' })));
        document.body.dataset.sessionsListed = String(list.length);
        const failed = stats.filter((r) => r.status === 'rejected');
        if (failed.length) setStatus(status, `stats failed for ${failed.length} session(s): ${failed[0].reason.message}`, true);
        else setStatus(status, `updated ${clock()}`);
      } catch (e) {
        // A 401 is no failure to report: the login form is all the page shows until then.
        if (e.status === 401) { setStatus(status, ''); F.showLogin(); } else setStatus(status, `cannot list sessions: ${e.message} (retrying)`, true);
      }
    }
    // Chained rather than setInterval so a slow server never gets overlapping refreshes.
    (async function loop() { await refresh(); setTimeout(loop, 2000); })();
    F.startHealth();
  }

  // ---------------------------------------------------------------- trajectory
  function trajectoryView(canvas) {
    const show = { initial: $('show-initial'), loops: $('show-loops'), points: $('show-points'), residuals: $('show-residuals') };
    const threshold = $('residual-threshold'), ellipseScale = $('ellipse-scale');
    let ellipses = new Map(), onPick = () => {};
    const projection = $('projection');
    const ORBIT = { yaw: -0.6, pitch: 0.9 };
    // pivot: the 3D point the projection is centred on (and orbits about); (u0, v0): the projected
    // point at the canvas centre; scale: pixels per metre. auto: refit on every draw until the user moves the view.
    const view = { pivot: [0, 0, 0], u0: 0, v0: 0, scale: 1, yaw: ORBIT.yaw, pitch: ORBIT.pitch, auto: true };
    let graph = null, error = null, index = new Map(), bounds = null, kind = '', loops = 0;
    const schedule = perFrame(draw);

    const is3d = () => (graph ? graph.dimension === 3 : /3d|bundle|sliding/.test(kind));
    const mode = () => (is3d() ? projection.value : 'top');
    const valid = (p) => Array.isArray(p) && num(p[0]) && num(p[1]);
    const isBA = () => kind === 'bundle_adjustment' || (graph && graph.points.length > 0);

    // Screen-right and screen-up unit vectors in world coordinates.
    function axes() {
      switch (mode()) {
        case 'front': return [[1, 0, 0], [0, 0, 1]];
        case 'side': return [[0, 1, 0], [0, 0, 1]];
        case 'orbit': {
          const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw), cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
          return [[cy, -sy, 0], [sy * sp, cy * sp, cp]];
        }
        default: return [[1, 0, 0], [0, 1, 0]];
      }
    }

    // Landmarks often include far outliers; fitting to the 1st-99th percentile keeps the cameras visible.
    function computeBounds() {
      const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
      const take = (p) => {
        if (!valid(p)) return;
        for (let i = 0; i < 3; i++) { const v = num(p[i]) ? p[i] : 0; if (v < lo[i]) lo[i] = v; if (v > hi[i]) hi[i] = v; }
      };
      for (const p of graph.poses) { take(p.position); if (show.initial.checked) take(p.initial); }
      if (show.points.checked && graph.points.length) {
        const pts = graph.points.map((p) => p.position).filter(valid);
        for (let i = 0; i < 3 && pts.length; i++) {
          const vs = pts.map((p) => (num(p[i]) ? p[i] : 0)).sort((a, b) => a - b);
          lo[i] = Math.min(lo[i], vs[Math.floor(vs.length * 0.01)]);
          hi[i] = Math.max(hi[i], vs[Math.ceil(vs.length * 0.99) - 1]);
        }
      }
      return lo[0] <= hi[0] ? { lo, hi } : null;
    }

    function fit(w, h) {
      bounds = bounds || computeBounds();
      if (!bounds) return;
      const { lo, hi } = bounds, ext = [0, 1, 2].map((i) => hi[i] - lo[i]);
      view.pivot = [0, 1, 2].map((i) => (lo[i] + hi[i]) / 2);
      view.u0 = view.v0 = 0;
      const [a, b] = axes();
      let du, dv;
      if (mode() === 'orbit') du = dv = Math.hypot(...ext); // rotation-invariant, so orbiting doesn't "breathe"
      else { du = Math.abs(a[0]) * ext[0] + Math.abs(a[1]) * ext[1] + Math.abs(a[2]) * ext[2]; dv = Math.abs(b[0]) * ext[0] + Math.abs(b[1]) * ext[1] + Math.abs(b[2]) * ext[2]; }
      const pad = 24, sx = (w - 2 * pad) / du, sy = (h - 2 * pad) / dv;
      const s = Math.min(du > 1e-9 ? sx : Infinity, dv > 1e-9 ? sy : Infinity);
      view.scale = Number.isFinite(s) && s > 0 ? s : 50;
    }

    function draw() {
      const { ctx, w, h } = fitCanvas(canvas);
      if (!graph) return centredText(ctx, w, h, error || 'loading graph…');
      if (view.auto) fit(w, h);
      const [a, b] = axes(), s = view.scale, [X, Y] = projector(w, h);
      const polyline = (field, style, width) => {
        ctx.beginPath();
        let pen = false;
        for (const p of graph.poses) {
          const q = p[field];
          if (!valid(q)) { pen = false; continue; }
          if (pen) ctx.lineTo(X(q), Y(q)); else ctx.moveTo(X(q), Y(q));
          pen = true;
        }
        ctx.strokeStyle = style; ctx.lineWidth = width; ctx.lineJoin = 'round'; ctx.stroke();
      };

      let pointsDrawn = 0;
      if (show.points.checked && graph.points.length) {
        ctx.fillStyle = 'rgba(40, 40, 40, 0.45)';
        for (const p of graph.points) {
          if (!valid(p.position)) continue;
          ctx.fillRect(X(p.position) - 0.75, Y(p.position) - 0.75, 1.5, 1.5);
          pointsDrawn++;
        }
      }
      if (show.initial.checked) polyline('initial', '#e39a4c', 1.5);
      if (show.residuals.checked) drawResiduals(ctx, X, Y);
      else if (show.loops.checked) {
        ctx.beginPath();
        for (const e of graph.edges) {
          const i = index.get(e[0]), j = index.get(e[1]);
          if (i === undefined || j === undefined || Math.abs(i - j) <= 1) continue; // consecutive = odometry
          const p = graph.poses[i].position, q = graph.poses[j].position;
          if (!valid(p) || !valid(q)) continue;
          ctx.moveTo(X(p), Y(p)); ctx.lineTo(X(q), Y(q));
        }
        ctx.strokeStyle = 'rgba(208, 49, 45, 0.45)'; ctx.lineWidth = 1; ctx.stroke();
      }
      polyline('position', '#1f3a93', isBA() ? 1 : 2);

      let posesDrawn = 0;
      const r = isBA() ? 3.5 : graph.poses.length <= 400 ? 2 : 0;
      ctx.fillStyle = '#1f3a93'; ctx.strokeStyle = '#fff'; ctx.lineWidth = 1;
      for (const p of graph.poses) {
        if (!valid(p.position)) continue;
        posesDrawn++;
        if (!r) continue;
        ctx.beginPath(); ctx.arc(X(p.position), Y(p.position), r, 0, 2 * Math.PI); ctx.fill();
        if (r > 2) ctx.stroke();
      }
      drawEllipses(ctx, X, Y, s);
      if (!graph.poses.length && !graph.points.length) centredText(ctx, w, h, 'no variables yet');
      else { scaleBar(ctx, h, s); axisTriad(ctx, w, h, a, b); }
      document.body.dataset.trajectoryPoints = String(posesDrawn);
      document.body.dataset.pointsDrawn = String(pointsDrawn);
    }

    // Every edge, grey below the χ² threshold and red above it (outliers), wider the worse.
    function drawResiduals(ctx, X, Y) {
      const limit = Number(threshold.value), chi = graph.edge_chi2 || [];
      let over = 0;
      for (const bad of [false, true]) {
        ctx.beginPath();
        graph.edges.forEach((e, k) => {
          const c = chi[k], i = index.get(e[0]), j = index.get(e[1]);
          if ((num(c) && c > limit) !== bad || i === undefined || j === undefined) return;
          const p = graph.poses[i].position, q = graph.poses[j].position;
          if (!valid(p) || !valid(q)) return;
          if (bad) over++;
          ctx.moveTo(X(p), Y(p)); ctx.lineTo(X(q), Y(q));
        });
        ctx.strokeStyle = bad ? 'rgba(214, 39, 40, 0.9)' : 'rgba(120, 130, 140, 0.35)'; ctx.lineWidth = bad ? 2 : 1; ctx.stroke();
      }
      document.body.dataset.edgesOverThreshold = String(over);
    }

    // World point -> canvas pixel, for the current view (x right, y down).
    function projector(w, h) {
      const [a, b] = axes(), pv = view.pivot, s = view.scale;
      const rel = (p) => [p[0] - pv[0], p[1] - pv[1], (num(p[2]) ? p[2] : 0) - pv[2]];
      const dot = (u, v) => u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
      return [(p) => w / 2 + (dot(a, rel(p)) - view.u0) * s, (p) => h / 2 - (dot(b, rel(p)) - view.v0) * s];
    }

    // 95% ellipses (2.45σ in 2D) of the selected variables' world position covariance (3×3),
    // projected on the view's screen axes: the 2×2 [a b]ᵀ Σ [a b] (a: right, b: up).
    function drawEllipses(ctx, X, Y, s) {
      let drawn = 0;
      const k = 2.4477 * Number(ellipseScale.value || 1), [u, v] = axes();
      const quad = (l, c, r) => [0, 1, 2].reduce((sum, i) => sum + l[i] * [0, 1, 2].reduce((t, j) => t + c[i][j] * r[j], 0), 0);
      for (const [key, c] of ellipses) {
        const i = index.get(key), p = i === undefined ? null : graph.poses[i].position;
        if (!valid(p)) continue;
        const [a, b, d] = [quad(u, c, u), quad(u, c, v), quad(v, c, v)], m = (a + d) / 2, r = Math.sqrt(((a - d) / 2) ** 2 + b * b);
        const r1 = Math.sqrt(Math.max(m + r, 0)) * k * s, r2 = Math.sqrt(Math.max(m - r, 0)) * k * s;
        ctx.beginPath(); ctx.ellipse(X(p), Y(p), Math.max(r1, 1), Math.max(r2, 1), -0.5 * Math.atan2(2 * b, a - d), 0, 2 * Math.PI);
        ctx.fillStyle = 'rgba(42, 157, 143, 0.18)'; ctx.fill();
        ctx.strokeStyle = '#2a9d8f'; ctx.lineWidth = 1.5; ctx.stroke();
        drawn++;
      }
      document.body.dataset.ellipsesDrawn = String(drawn);
    }

    // The pose nearest a click (within 10 px), for the ellipses.
    function pick(e) {
      if (!graph) return;
      const rect = canvas.getBoundingClientRect(), [X, Y] = projector(rect.width, rect.height);
      let best = null, bestD = 10;
      for (const p of graph.poses) {
        if (!valid(p.position)) continue;
        const dist = Math.hypot(X(p.position) - (e.clientX - rect.left), Y(p.position) - (e.clientY - rect.top));
        if (dist < bestD) { bestD = dist; best = p.key; }
      }
      if (best !== null) onPick(best);
    }

    function scaleBar(ctx, h, s) {
      const len = niceStep(100 / s), px = len * s, x = 16, y = h - 16;
      ctx.strokeStyle = '#333'; ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 5); ctx.stroke();
      ctx.fillStyle = '#333'; ctx.textAlign = 'center'; ctx.textBaseline = 'bottom';
      ctx.fillText(fmtLength(len), x + px / 2, y - 3);
    }

    // Which world axes point where: essential once the view is orbited.
    function axisTriad(ctx, w, h, a, b) {
      const ox = w - 40, oy = h - 34, L = 22;
      [['x', 0, '#c0392b'], ['y', 1, '#27ae60'], ['z', 2, '#2c6fbb']].forEach(([name, i, color]) => {
        if (i === 2 && !is3d()) return;
        const dx = a[i] * L, dy = -b[i] * L;
        if (Math.hypot(dx, dy) < 4) return; // axis points at the viewer
        ctx.strokeStyle = ctx.fillStyle = color; ctx.lineWidth = 1.5;
        ctx.beginPath(); ctx.moveTo(ox, oy); ctx.lineTo(ox + dx, oy + dy); ctx.stroke();
        ctx.textAlign = 'center'; ctx.textBaseline = 'middle';
        ctx.fillText(name, ox + dx * 1.35, oy + dy * 1.35);
      });
    }

    // Pan/zoom change only (u0, v0, scale); orbit changes yaw/pitch about the pivot.
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      const rect = canvas.getBoundingClientRect();
      const mx = e.clientX - rect.left - rect.width / 2, my = e.clientY - rect.top - rect.height / 2;
      const u = view.u0 + mx / view.scale, v = view.v0 - my / view.scale; // keep this point under the cursor
      view.scale *= Math.exp(-e.deltaY * (e.deltaMode ? 0.05 : 0.0015));
      view.u0 = u - mx / view.scale; view.v0 = v + my / view.scale;
      view.auto = false;
      schedule();
    }, { passive: false });
    let drag = null;
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      drag = { x0: e.clientX, y0: e.clientY, x: e.clientX, y: e.clientY, rotate: mode() === 'orbit' && !e.shiftKey && e.button === 0 };
      canvas.setPointerCapture(e.pointerId);
      canvas.classList.add('dragging');
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (drag.rotate) {
        view.yaw += dx * 0.01;
        view.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2, view.pitch + dy * 0.01));
      } else {
        view.u0 -= dx / view.scale; view.v0 += dy / view.scale;
        view.auto = false;
      }
      schedule();
    });
    const endDrag = () => { drag = null; canvas.classList.remove('dragging'); };
    canvas.addEventListener('pointerup', (e) => {
      if (drag && Math.hypot(e.clientX - drag.x0, e.clientY - drag.y0) < 4) pick(e); // a click, not a drag
      endDrag();
    });
    canvas.addEventListener('pointercancel', endDrag);

    function reset() {
      view.auto = true;
      if (mode() === 'orbit') Object.assign(view, ORBIT, { auto: true });
      $('hint').textContent = mode() === 'orbit' ? 'drag: rotate · shift-drag or right-drag: pan · wheel: zoom' : 'drag: pan · wheel: zoom';
      schedule();
    }
    $('reset-view').addEventListener('click', reset);
    projection.addEventListener('change', reset);
    for (const box of Object.values(show)) box.addEventListener('change', () => { bounds = null; schedule(); });
    threshold.addEventListener('input', schedule);
    ellipseScale.addEventListener('change', schedule);
    new ResizeObserver(schedule).observe(canvas);

    return {
      setKind(k) {
        kind = k || '';
        $('projection-control').hidden = !is3d();
        $('points-control').hidden = !isBA();
        schedule();
      },
      setGraph(g) {
        const poses = (g.poses || []).slice().sort((p, q) => p.key - q.key);
        graph = { ...g, poses, points: g.points || [], edges: g.edges || [] };
        index = new Map(poses.map((p, i) => [p.key, i]));
        loops = graph.edges.filter((e) => { const i = index.get(e[0]), j = index.get(e[1]); return i !== undefined && j !== undefined && Math.abs(i - j) > 1; }).length;
        bounds = null; error = null;
        $('projection-control').hidden = !is3d();
        $('points-control').hidden = !isBA();
        $('graph-info').textContent = `${poses.length} poses` + (graph.points.length ? ` · ${graph.points.length} points` : '') +
          (graph.edges.length ? ` · ${graph.edges.length} edges (${loops} loop closures)` : '') + (num(g.sequence) ? ` · sequence ${g.sequence}` : '');
        schedule();
      },
      setEllipses(map) { ellipses = map; schedule(); },
      onPick(fn) { onPick = fn; },
      poses: () => (graph ? graph.poses.map((p) => p.key) : []),
      is3d,
      setError(message) {
        if (graph) $('graph-info').textContent = `graph refresh failed: ${message}`;
        else { error = `graph unavailable: ${message}`; schedule(); }
      },
    };
  }

  // ---------------------------------------------------------------- session page
  function startSession() {
    const id = decodeURIComponent(location.pathname.replace(/^\/sessions\//, '').replace(/\/+$/, ''));
    document.title = `factord · ${id}`;
    $('name').textContent = id;
    const status = $('status'), logList = $('log');
    const traj = trajectoryView($('trajectory'));
    const plot = F.convergencePlot($('convergence'));
    const timeline = F.timelinePlot($('timeline'));
    plot.schedule();
    F.startOperator(id, traj);

    let statsBusy = false, seeded = false;
    async function refreshStats() {
      if (statsBusy) return;
      statsBusy = true;
      try {
        const s = await getJSON(api(id));
        if (!seeded) {
          seeded = true;
          traj.setKind(s.kind);
          $('kind').textContent = s.kind || '?';
          $('kind').hidden = false;
          if (s.last_summary) plot.addSummary(num(s.solves) ? s.solves : 'loaded', s.last_summary);
        }
        const sum = s.last_summary;
        const item = (label, value) => el('span', {}, label + ' ', el('b', { textContent: value }));
        $('stats').replaceChildren(statusEl(s),
          item('variables', fmtInt(s.num_variables)), item('factors', fmtInt(s.num_factors)),
          item('cost χ²', fmtCost(s.chi2)), item('last solve', fmtMs(solveSeconds(sum))),
          item('iterations', fmtInt(iterationCount(sum))), item('solves', fmtInt(s.solves)),
          item('sequence', `${fmtInt(s.solved_sequence)} / ${fmtInt(s.sequence)}`),
          ...(s.pending_batches ? [item('pending batches', fmtInt(s.pending_batches))] : []),
          ...(s.instance ? [item('instance', s.instance)] : []), // in a fleet: the owner
          ...incrementalItems(sum && sum.used && sum.used.incremental, item));
        setStatus(status, `updated ${clock()}`);
      } catch (e) {
        if (e.status === 401) { setStatus(status, ''); F.showLogin(); } else setStatus(status, `cannot load session stats: ${e.message} (retrying)`, true);
      } finally {
        statsBusy = false;
      }
    }
    (async function loop() { await refreshStats(); setTimeout(loop, 2000); })();

    // Graph refetch: at most one request in flight and one start per 500 ms; requests
    // arriving meanwhile collapse into a single follow-up.
    let graphBusy = false, graphWanted = false, graphTimer = 0, graphStarted = -Infinity;
    function requestGraph() {
      graphWanted = true;
      if (graphBusy || graphTimer) return;
      const wait = graphStarted + 500 - performance.now();
      if (wait > 0) { graphTimer = setTimeout(() => { graphTimer = 0; requestGraph(); }, wait); return; }
      graphWanted = false; graphBusy = true; graphStarted = performance.now();
      getJSON(api(id, '/graph'))
        .then((g) => traj.setGraph(g), (e) => traj.setError(e.message))
        .finally(() => { graphBusy = false; if (graphWanted) requestGraph(); });
    }
    requestGraph();

    // Newest first; `at`: when the server published it (history), else now.
    function log(kind, text, at) {
      const time = at ? new Date(at).toLocaleTimeString() : clock();
      logList.prepend(el('li', { className: kind }, el('time', { textContent: time }), text));
      while (logList.children.length > 50) logList.lastChild.remove();
      document.body.dataset.logEntries = String(logList.children.length);
    }
    const events = new EventSource(api(id, '/events'));
    const conn = $('conn');
    events.onopen = () => { document.body.dataset.eventsConnected = 'true'; conn.textContent = '(live)'; };
    events.onerror = () => { conn.textContent = '(disconnected, retrying…)'; };
    // The same handlers take the live stream and, on load, the server's history of it; an
    // event in both (published while the page loaded) is shown once.
    const shown = new Set(), handlers = {};
    const on = (name, fn) => {
      handlers[name] = (d, at) => {
        const key = name + JSON.stringify(d);
        if (name !== 'stats' && name !== 'poses') {
          if (shown.has(key)) return;
          if (shown.size > 2000) shown.clear(); // overlap is only possible at load
          shown.add(key);
        }
        fn(d, at);
      };
      events.addEventListener(name, (ev) => {
        let d;
        try { d = JSON.parse(ev.data); } catch (_) { d = { raw: ev.data }; }
        handlers[name](d || {});
      });
    };
    on('stats', (d) => plot.addIteration(d));
    on('poses', requestGraph);
    on('window', requestGraph); // sliding_window sessions announce their keyframes this way
    on('summary', (d, at) => {
      const s = d.summary || {};
      plot.addSummary(d.solve, s);
      const [cls, text] = F.describeSummary(d.solve, s);
      log(cls, text, at);
      refreshStats();
      history.refresh();
    });
    on('acks', (d, at) => log('acks', `batch ${fmtInt(d.sequence)} accepted` + (Array.isArray(d.factor_ids) ? ` (${d.factor_ids.length} factors)` : ''), at));
    on('errors', (d, at) => {
      log('errors', F.describeError(d), at);
      history.refresh();
    });
    const history = F.sessionHistory(id, timeline, handlers);
    on('lagged', (d) => { log('lagged', `fell behind: missed ${fmtInt(d.skipped)} events`); requestGraph(); });
  }

  // plots.js and operator.js add to `factord` before the page is parsed to its end.
  document.addEventListener('DOMContentLoaded', () => {
    if (document.body.dataset.page === 'session') startSession();
    else startIndex();
  });
})();

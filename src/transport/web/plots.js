'use strict';
// factord web UI: the session page's plots, the live convergence plot (per iteration) and the
// session's timeline (per solve: χ², solve time, update latency), on `window.factord`.
(() => {
  const F = window.factord;
  const { num, fitCanvas, perFrame, decade, iterationLog } = F;

  // ---------------------------------------------------------------- convergence plot
  function convergencePlot(canvas) {
    const MAX = 2000, COLORS = ['#1f3a93', '#2a9d8f'];
    let pts = [], x = 0, band = 0, lastSolve;
    const seen = new Set(); // solves with live iterations, so their summary doesn't add them twice
    const schedule = perFrame(draw);
    new ResizeObserver(schedule).observe(canvas);

    function add(report, solve) {
      if (solve !== lastSolve) { band++; lastSolve = solve; }
      pts.push({ x: ++x, chi2: report.chi2, trial: report.trial_chi2, ok: report.accepted !== false, band, solve });
      if (pts.length > MAX) pts = pts.slice(pts.length - MAX);
    }

    function draw() {
      const { ctx, w, h } = fitCanvas(canvas);
      const L = 58, R = 12, T = 10, B = 34, pw = w - L - R, ph = h - T - B;
      ctx.fillStyle = '#444'; ctx.textAlign = 'center'; ctx.textBaseline = 'bottom';
      // The x axis runs over solves, each one's iterations left to right in its own colour band:
      // ticks mark where a solve starts, labelled with its number.
      ctx.fillText('solve (its iterations left to right)', L + pw / 2, h - 2);
      ctx.save(); ctx.translate(12, T + ph / 2); ctx.rotate(-Math.PI / 2); ctx.textBaseline = 'middle';
      ctx.fillText('cost (χ²)', 0, 0); ctx.restore();
      ctx.strokeStyle = '#c4c9d0'; ctx.lineWidth = 1; ctx.strokeRect(L + 0.5, T + 0.5, pw, ph);
      document.body.dataset.plotIterations = String(pts.length);
      document.body.dataset.plotSolves = String(new Set(pts.map((p) => p.band)).size);
      if (!pts.length) { ctx.fillStyle = '#66707c'; ctx.textBaseline = 'middle'; ctx.fillText('no iterations yet', L + pw / 2, T + ph / 2); return; }

      const vals = [];
      for (const p of pts) { vals.push(p.chi2); if (!p.ok) vals.push(p.trial); }
      const pos = vals.filter((v) => num(v) && v > 0);
      let lo = pos.length ? Math.floor(Math.log10(Math.min(...pos))) : -1;
      let hi = pos.length ? Math.ceil(Math.log10(Math.max(...pos))) : 1;
      if (hi <= lo) hi = lo + 1;
      const x0 = pts[0].x, x1 = Math.max(pts[pts.length - 1].x, x0 + 1);
      const px = (xv) => L + 6 + ((xv - x0) / (x1 - x0)) * (pw - 12); // inset so end markers aren't clipped
      // Non-positive cost sits on the floor, a non-finite trial on the ceiling.
      const py = (v) => (num(v) && v > 0 ? T + ph - ((Math.log10(v) - lo) / (hi - lo)) * ph : v > 0 ? T : T + ph);

      ctx.textBaseline = 'middle'; ctx.textAlign = 'right';
      const every = Math.max(1, Math.ceil((hi - lo) / (ph / 18)));
      for (let k = lo; k <= hi; k++) {
        const y = Math.round(py(Math.pow(10, k))) + 0.5;
        ctx.strokeStyle = '#d5d9de'; ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(L + pw, y); ctx.stroke();
        if ((k - lo) % every === 0) { ctx.fillStyle = '#444'; ctx.fillText(decade(k), L - 6, y); }
        if (k < hi && hi - lo <= 6) { // minor 2..9 lines while they stay readable
          ctx.strokeStyle = '#f0f2f4'; ctx.beginPath();
          for (let m = 2; m <= 9; m++) { const ym = Math.round(py(m * Math.pow(10, k))) + 0.5; ctx.moveTo(L, ym); ctx.lineTo(L + pw, ym); }
          ctx.stroke();
        }
      }
      ctx.textAlign = 'center'; ctx.textBaseline = 'top'; ctx.fillStyle = '#444';
      let labelled = -Infinity, ticks = 0;
      for (let i = 0; i < pts.length; i++) {
        if (i > 0 && pts[i].band === pts[i - 1].band) continue;
        const xx = Math.round(px(pts[i].x)) + 0.5;
        ctx.strokeStyle = '#eceef1'; ctx.beginPath(); ctx.moveTo(xx, T); ctx.lineTo(xx, T + ph); ctx.stroke();
        if (xx - labelled >= 48) { // as many labels as fit
          ctx.fillText(String(pts[i].solve), xx, T + ph + 4);
          labelled = xx; ticks++;
        }
      }
      document.body.dataset.plotSolveLabels = String(ticks);

      ctx.save();
      ctx.beginPath(); ctx.rect(L, T - 4, pw + 4, ph + 8); ctx.clip();
      ctx.lineWidth = 1.5;
      for (let i = 0; i < pts.length;) { // one polyline per solve
        let j = i;
        ctx.beginPath(); ctx.strokeStyle = COLORS[pts[i].band % 2];
        for (; j < pts.length && pts[j].band === pts[i].band; j++) {
          if (j === i) ctx.moveTo(px(pts[j].x), py(pts[j].chi2)); else ctx.lineTo(px(pts[j].x), py(pts[j].chi2));
        }
        ctx.stroke();
        i = j;
      }
      const r = pts.length > 300 ? 1.6 : 2.6;
      for (const p of pts) {
        ctx.beginPath(); ctx.arc(px(p.x), py(p.ok ? p.chi2 : p.trial), p.ok ? r : r + 1, 0, 2 * Math.PI);
        if (p.ok) { ctx.fillStyle = COLORS[p.band % 2]; ctx.fill(); } else { ctx.strokeStyle = '#d0312d'; ctx.lineWidth = 1.3; ctx.stroke(); }
      }
      ctx.restore();
    }

    return {
      addIteration(d) { seen.add(d.solve); add(d, d.solve); schedule(); },
      // A summary for a solve whose iterations we missed (page opened mid-solve, lagged stream) fills them in.
      addSummary(solve, summary) {
        if (seen.has(solve)) return;
        seen.add(solve);
        for (const r of iterationLog(summary)) add(r, solve);
        schedule();
      },
      schedule,
    };
  }


  F.convergencePlot = convergencePlot;

  // ---------------------------------------------------------------- timeline
  // Two panels over wall-clock time: χ² (log) above, solve time and update latency (log ms) below.
  function timelinePlot(canvas) {
    const COLORS = { chi2: '#1f3a93', solve: '#e76f51', latency: '#2a9d8f' };
    let pts = [];
    const schedule = perFrame(draw);
    new ResizeObserver(schedule).observe(canvas);

    function logRange(vals) {
      const pos = vals.filter((v) => num(v) && v > 0);
      if (!pos.length) return [-1, 1];
      const hi = Math.ceil(Math.log10(Math.max(...pos)));
      // At most eight decades: a first solve's χ² of 1e-40 would flatten the rest.
      const lo = Math.max(Math.floor(Math.log10(Math.min(...pos))), hi - 8);
      return [lo, hi > lo ? hi : lo + 1];
    }

    function panel(ctx, L, T, pw, ph, series, label, t0, t1) {
      const [lo, hi] = logRange(series.flatMap((s) => s.values));
      const px = (t) => L + 4 + ((t - t0) / Math.max(t1 - t0, 1)) * (pw - 8);
      const py = (v) => T + ph - (Math.max(Math.log10(v) - lo, 0) / (hi - lo)) * ph;
      ctx.strokeStyle = '#c4c9d0'; ctx.lineWidth = 1; ctx.strokeRect(L + 0.5, T + 0.5, pw, ph);
      ctx.fillStyle = '#444'; ctx.textAlign = 'right'; ctx.textBaseline = 'middle';
      const every = Math.max(1, Math.ceil((hi - lo) / (ph / 16)));
      for (let k = lo; k <= hi; k += every) {
        const y = Math.round(py(Math.pow(10, k))) + 0.5;
        ctx.strokeStyle = '#e3e6ea'; ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(L + pw, y); ctx.stroke();
        ctx.fillText(decade(k), L - 5, y);
      }
      ctx.save(); ctx.translate(11, T + ph / 2); ctx.rotate(-Math.PI / 2); ctx.textAlign = 'center';
      ctx.fillText(label, 0, 0); ctx.restore();
      for (const s of series) {
        ctx.strokeStyle = ctx.fillStyle = s.color; ctx.lineWidth = 1.5; ctx.beginPath();
        let pen = false;
        pts.forEach((p, i) => {
          const v = s.values[i];
          if (!num(v) || v <= 0) { pen = false; return; }
          if (pen) ctx.lineTo(px(p.unix_ms), py(v)); else ctx.moveTo(px(p.unix_ms), py(v));
          pen = true;
        });
        ctx.stroke();
        if (pts.length <= 200) pts.forEach((p, i) => { const v = s.values[i]; if (num(v) && v > 0) ctx.fillRect(px(p.unix_ms) - 1.5, py(v) - 1.5, 3, 3); });
      }
    }

    function draw() {
      const { ctx, w, h } = fitCanvas(canvas);
      document.body.dataset.timelinePoints = String(pts.length);
      if (!pts.length) { ctx.fillStyle = '#66707c'; ctx.textAlign = 'center'; ctx.fillText('no solves yet', w / 2, h / 2); return; }
      const L = 58, R = 12, T = 8, B = 34, gap = 14, pw = w - L - R, ph = (h - T - B - gap) / 2;
      const t0 = pts[0].unix_ms, t1 = pts[pts.length - 1].unix_ms;
      panel(ctx, L, T, pw, ph, [{ values: pts.map((p) => p.chi2), color: COLORS.chi2 }], 'χ²', t0, t1);
      const ms = (k) => pts.map((p) => (num(p[k]) ? p[k] * 1000 : null));
      panel(ctx, L, T + ph + gap, pw, ph, [{ values: ms('solve_seconds'), color: COLORS.solve },
        { values: ms('latency_seconds'), color: COLORS.latency }], 'ms', t0, t1);
      ctx.textAlign = 'center'; ctx.textBaseline = 'top'; ctx.fillStyle = '#444';
      const span = (t1 - t0) / 1000;
      ctx.fillText(new Date(t0).toLocaleTimeString(), L + 40, h - B + 6);
      ctx.fillText(new Date(t1).toLocaleTimeString(), L + pw - 40, h - B + 6);
      ctx.fillText(`${pts.length} solves over ${span < 120 ? span.toFixed(1) + ' s' : (span / 60).toFixed(1) + ' min'}`, L + pw / 2, h - B + 6);
      let x = L;
      for (const [name, color] of [['χ²', COLORS.chi2], ['solve time', COLORS.solve], ['update latency', COLORS.latency]]) {
        ctx.fillStyle = color; ctx.fillRect(x, h - 12, 10, 3); ctx.fillStyle = '#444'; ctx.textAlign = 'left';
        ctx.fillText(name, x + 14, h - 17); x += ctx.measureText(name).width + 34;
      }
    }

    return { setPoints(points) { pts = points.slice(); schedule(); }, schedule };
  }
  F.timelinePlot = timelinePlot;
})();

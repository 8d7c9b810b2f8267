// The policy's plan, drawn the same way on the live view and the episode viewer: μ over the
// horizon as a line and ±σ as a band, steering blue and throttle orange, on [-1, 1].
"use strict";
function drawPlan(canvas, note, plan, whyNone) {
  const g = canvas.getContext("2d"), W = canvas.width, H = canvas.height;
  g.clearRect(0, 0, W, H);
  g.strokeStyle = "#444"; g.lineWidth = 1; g.beginPath(); g.moveTo(0, H / 2); g.lineTo(W, H / 2); g.stroke();
  if (!plan) { note.textContent = whyNone; return; }
  note.textContent = "blue: steering, orange: throttle; band: ±σ";
  const n = plan.mu.length, X = (k) => 10 + k * (W - 20) / Math.max(1, n - 1), Y = (v) => H / 2 - v * (H / 2 - 6);
  [[0, "rgba(127,179,255,0.25)", "#7fb3ff"], [1, "rgba(255,170,80,0.25)", "#ffaa50"]].forEach(([j, band, line]) => {
    g.fillStyle = band; g.beginPath();
    for (let k = 0; k < n; k++) g.lineTo(X(k), Y(plan.mu[k][j] + plan.sigma[k][j]));
    for (let k = n - 1; k >= 0; k--) g.lineTo(X(k), Y(plan.mu[k][j] - plan.sigma[k][j]));
    g.fill(); g.strokeStyle = line; g.lineWidth = 2; g.beginPath();
    for (let k = 0; k < n; k++) g.lineTo(X(k), Y(plan.mu[k][j]));
    g.stroke(); g.lineWidth = 1;
  });
}

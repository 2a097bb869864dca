"""Classical separation methods the paper compares against, re-implemented from their papers.

Each module exposes ``separate(images, angles_deg, **params) -> (R̂, T̂)`` on an aligned stack
(N, H, W, C) float32 linear; single-image methods take the unpolarized image S0 from the
Stokes fit. Outputs are in urd's target units (R̂ + T̂ = S0 for the single-image methods).
"""

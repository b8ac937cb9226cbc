"""Judging reconstructions: PSNR/SSIM (:mod:`.metrics`), no-reference NIQE (:mod:`.niqe`),
scoring methods on simulated windows (:mod:`.scoring`) and on the real capture
(:mod:`.capture_quality`)."""

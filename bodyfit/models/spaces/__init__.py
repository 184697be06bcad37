"""Shape spaces grown from a user's own scans (BLiSS): registration in the current space, acceptance,
recomputed bone and identity PCA, and the asset folder that carries the grown space."""

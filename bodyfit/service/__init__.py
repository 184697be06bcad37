"""Transport-neutral service core (loads assets once; synthesize / fit / upgrade; validation; errors).

Depends on :mod:`bodyfit.models` only. Grows with the body-model, fitting and service issues.
"""

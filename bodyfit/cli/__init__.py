"""The ``bodyfit`` command line.

It sits above every other layer: against a server it drives the SDK (:mod:`bodyfit.clients`); in this
process (``bodyfit fit``, ``synth`` without ``--server``, ``upgrade``, ``batch-upgrade --backend local``,
``demo``, ``build-assets``) it calls the service and the models; ``bodyfit serve`` starts :mod:`bodyfit.api`.
Nothing below imports it. Commands: :mod:`.app`; ``bodyfit fit`` and its input kinds: :mod:`.fit`; batch
back-ends: :mod:`.backends`.
"""

from bodyfit.cli.app import app, main

__all__ = ["app", "main"]

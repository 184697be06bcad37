"""``bodyfit fit``: the body model fitted to files in this process, one subcommand per input kind.

``scan`` (meshes and scans: :mod:`.scan`), ``markers`` (motion-capture trials: :mod:`.markers`),
``sequence`` (registered mesh sequences: :mod:`.sequence`), and ``auto``, the default, which detects the
kind (:mod:`.kinds`). The commands are in :mod:`.commands`.
"""

"""Personal rigs: one person's body model built from several scans of them in different poses.

:func:`.build.build_rig` fits the scans' registrations with one shared shape and alternates the person's
rest-pose template offsets with the poses (:mod:`.build` cites the method); :class:`.subject.Subject` is the
portable result, one ``.npz`` checked against the body model it was built for when loaded.
"""

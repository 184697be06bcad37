"""Pure-torch model math, the skeleton, assets and exporters.

Conventions (one per concept, used everywhere in bodyfit):

* Units: metres and radians. Degrees appear only in OpenSim ``.mot`` files.
* World frame = OpenSim ground: +Y up, +X forward (the body faces +X at zero pose), +Z to the body's right.
* Pose = named generalized coordinates. A coordinate that exists in Rajagopal2015 keeps its OpenSim name,
  range and meaning, so ``q = 0`` is OpenSim's neutral pose. Extra coordinates (thoracic and cervical spine,
  scapulae) have their own names and zero = neutral.
* Global translation ("root", metres) is separate from the named coordinates: ``root = (pelvis_tx,
  pelvis_ty, pelvis_tz)``.
* Rigid transforms are 4x4 homogeneous matrices ``[[R, t], [0, 1]]`` mapping body coordinates to world
  coordinates. Frame orientations read from OpenSim are XYZ body-fixed Euler angles.
* Batch first: tensor functions take ``(B, ...)`` and return ``(B, ...)``; dtype and device follow the inputs.
* Model objects hold buffers only; optimisation state lives in the fitters.
"""

"""The simulated world: scenes that simulate only the effects they call for.

- ``sim.effects``: the effect registry (:data:`sim.effects.EFFECTS`) and the check of a scene's
  effects against it; the scene file itself is ``workcell.scene``.
- ``sim.world``: :class:`sim.world.SimWorld` (Open3D ray casting: depth frames, grasp contact);
  ``SimWorld.from_file`` reads and checks a scene file completely. Its parts: ``sim.meshes``
  (object meshes, placement, micro-relief), ``sim.depth_render`` (the depth cameras) and
  ``sim.grasp_contact`` (the gels: contact, indentation, gap maps).
- ``sim.depth_effects``: Kinect v2 depth effects; ``sim.arm``: arm motion model.
- ``sim.gelsight``: the GelSight renderer; ``sim.gelsight_calibration`` the sensor calibration it
  reads; ``sim.gelsight_effects`` its optional effects.
- ``sim.registration_check``, ``sim.gelsight_check``: perception and the renderer checked
  against the simulated ground truth and real presses.
- ``sim.ur_controller``: a fake UR e-Series controller (RTDE, dashboard and script server)
  that the real ur_rtde client drives in the UR backend's tests and benchmarks.

``import sim.gelsight`` does not load Open3D.
"""

"""sim: the endoscope simulator (Mitsuba 3 renders of phantoms with ground truth).

Modules: ``config`` (:class:`SimConfig` + YAML), its sections ``config_scope`` (camera,
light, sensor), ``config_tissue`` (appearance, cut faces, randomisation),
``config_paths`` (paths, tracking), ``config_effects`` (tools, smoke, blur, lens smear)
and their shared ``config_checks``, ``errors`` (the simulator's errors),
``mitsuba_camera`` (the one conversion from Mitsuba's camera/depth conventions),
``render`` (one scene per mesh), ``spot_direct`` (the tip light's direct lighting along
the exact distorted pixel rays), ``imaging`` (field stop, vignetting, sensor noise),
``appearance`` (procedural 3D texture, randomisation), ``collision`` (distance to
tissue), ``paths`` (collision-checked camera paths), ``tracking`` (tracked-pose noise),
``retrack`` (the same frames with another tracking noise), ``phantom`` (phantom.json
reader), ``synthetic`` (a tiny hand-made phantom for tests), ``pipeline`` (``sim
render``), ``nerfstudio`` (export), ``dataset`` (training sets), ``cli``. The Mitsuba
variant probe is ``chisel.core.mitsuba_variant``. Importing ``sim`` does not import
Mitsuba. See docs/sim.md.
"""

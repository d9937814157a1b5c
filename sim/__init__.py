"""sim: the endoscope simulator (Mitsuba 3 renders of phantoms with ground truth).

Modules: ``config`` (frozen configs + YAML), ``variant`` (Mitsuba variant probe),
``mitsuba_camera`` (the one conversion from Mitsuba's camera/depth conventions),
``render`` (one scene per mesh), ``imaging`` (field stop, vignetting, sensor noise),
``appearance`` (procedural 3D texture, randomisation), ``paths`` (collision-checked
camera paths), ``tracking`` (tracked-pose noise), ``phantom`` (phantom.json reader),
``pipeline`` (``sim render``), ``nerfstudio`` (export), ``dataset`` (training sets),
``cli``. Importing ``sim`` does not import Mitsuba. See docs/sim.md.
"""

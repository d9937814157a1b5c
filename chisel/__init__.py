"""Endoscopic Chisel: keep a preoperative sinus model true while surgery removes tissue.

The updater never imports the simulator (``sim``) or the phantom generator (``phantoms``):
it runs on real patient data.
"""

__version__ = "0.1.0"

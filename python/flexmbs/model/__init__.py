"""Describing and building a mechanism: the case format's schema (description.py) and files
(casefile.py), materials and sections (sections.py), time laws (laws.py), the compiled model's
flat arrays (arrays.py: Model, Body), the builder from a description (mechanism.py), joint
constraint rows (constraints.py), assembly and the rigid reference by position analysis
(kinematics.py), and fingerprints of a resolved description (fingerprint.py).

Nothing here simulates: this layer is below flexmbs.analysis.
"""

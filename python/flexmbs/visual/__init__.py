"""Pictures of a simulated mechanism: the overview figure (plots.py), the animation of the
motion (animation.py), the drawing of one instant shared by both (scene.py) and the ParaView
export (export.py)."""

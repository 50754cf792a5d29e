"""The continuum robot: its design as data, kinematics, statics (load sharing), reach, Table II and the
workspace, its open-loop plant and its mismatched rig.
"""

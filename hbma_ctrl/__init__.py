"""hbma-ctrl: model, observe and control Hyperelastic Ballooning Membrane Actuators (HBMA).

Layers, imports pointing down only (checked by ``lint-imports``)::

    hbma_ctrl.app        scenario files, scenes, protocol, metrics, plots, benches, CLI
    hbma_ctrl.runtime    tick(t, readings) -> commands: estimator + controller + safety, no I/O
    hbma_ctrl.estimators, hbma_ctrl.controllers
                         the roles (root folders estimators/ and controllers/, linked into the package)
    hbma_ctrl.robot      the continuum robot: design, kinematics, statics, reach, plant, rig
    hbma_ctrl.sim        trials, the batch simulator, the protocol's trials, the rig
    hbma_ctrl.models     fidelity ladder, reduced chamber model, tables, banks
    hbma_ctrl.core       units, validation, params, materials, physics, interfaces, codegen
"""

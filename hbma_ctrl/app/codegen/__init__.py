"""C code generation of a closed loop (``hbma-ctrl codegen``): :mod:`hbma_ctrl.core.loopgen` turns a
loop of named casadi Functions into C and runs it; :mod:`hbma_ctrl.app.codegen.chamber` and
:mod:`hbma_ctrl.app.codegen.robot` build that loop for a chamber and for the robot."""

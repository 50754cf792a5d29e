"""The physics core: units, validation, parameters, materials, the membrane and gas physics (casadi),
the role interfaces and the code generator. Imports nothing else of the package.
"""

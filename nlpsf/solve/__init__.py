"""The calculator: the two-of-three relation (``relation``), the magnitude scan
(``magnitude_scan``), the solver and its plan (``solver``), the answer (``solution``) and its
conditions (``conditions``), validity flags (``validity``), the model-uncertainty parts
(``model_part``, ``roman_uncertainty``), answers over the field (``over_field``), batches
(``batch``), the accuracy-driven choice of effects (``accuracy``) and the impact report
(``impact``).

``from nlpsf import solve`` is the solve function (``nlpsf.solve.solver.solve``), not this
package: import its modules by name (``from nlpsf.solve import solver``).
"""

"""A request, resolved once: the typed solve request and how it is read (``resolve``), the scene
presets, the Roman default among them (``presets``), and the shear budgets a tolerance can come
from (``shear``); a batch file's rows (``rows``).
"""

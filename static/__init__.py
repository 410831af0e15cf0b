"""The page (HTML, CSS, JS and vendored libraries), installed as package data of ``nlpsf.web``."""

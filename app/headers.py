"""The headers every response carries (the page, the API, refusals written before the application):
constants only, so that every module that answers -- ``errors``, ``security``, ``protocol`` -- takes
them from here and none of them imports another for them."""

from __future__ import annotations

#: The page and /docs load only their own files (JS libraries vendored); nothing may frame them.
#: Inline styles stay allowed: uPlot and Swagger UI set element styles.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
SECURITY_HEADERS = [
    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"permissions-policy", b"camera=(), microphone=(), geolocation=()"),
]

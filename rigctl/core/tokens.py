"""Access tokens: the one shared secret a service makes when it starts and checks on every request
that needs it. The daemon's console prints its token for the operator's page; an emulated bench
serving beyond loopback writes its backdoor's token into the rig file it writes (mode 0600), where
every client of that bench reads it.

A token is 24 random bytes, URL-safe base64 (32 characters: it goes in a URL's fragment or query
unescaped). A given token is compared in constant time, so how long a refusal takes says nothing
about how much of a guess was right.
"""

from __future__ import annotations

import secrets


def new_token() -> str:
    """A fresh random token (32 URL-safe characters)."""
    return secrets.token_urlsafe(24)


def token_matches(given: object, token: str) -> bool:
    """Whether `given` (what a request carried: anything, None when absent) is `token`."""
    return isinstance(given, str) and bool(given) and secrets.compare_digest(given.encode(),
                                                                             token.encode())

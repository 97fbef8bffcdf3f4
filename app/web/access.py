"""The app's access token: asked once per browser before anything of the app is sent to it.

On a host other than loopback the app requires a token (the same scheme as `knotlab serve`:
--token, else $KNOTLAB_TOKEN, else one generated and printed). A browser that connects gets only
a dialog asking for it; its tab (scene, panels, labelling state) is built only once the token
matched, and the browser keeps the token in its local storage, so it is asked once.
"""

from __future__ import annotations

import hmac
import logging
import threading
import time
from collections.abc import Callable

import viser

log = logging.getLogger(__name__)
TOKEN_KEY = "knotlab.token"  # browser local storage key of the accepted token
WRONG_PAUSE_S = 1.0  # a wrong token waits this long before the dialog answers (no fast guessing)


def token_matches(given: str | None, token: str) -> bool:
    """True when ``given`` is the token (compared in constant time)."""
    return given is not None and hmac.compare_digest(given.strip().encode(), token.encode())


class AccessGate:
    """One connected client that has not shown the token yet; ``admit`` runs once it has."""

    def __init__(self, client: viser.ClientHandle, token: str, admit: Callable[[], None]) -> None:
        self.client = client
        self._token = token
        self._admit = admit
        self._once = threading.Lock()
        self.admitted = False

    def open(self) -> None:
        """Admit a browser that kept the token; otherwise ask for it."""
        try:
            kept = self.client.local_storage.get_item(TOKEN_KEY, timeout=3.0)
        except (RuntimeError, TimeoutError):
            kept = None
        if token_matches(kept, self._token):
            self._pass()
        else:
            self._ask()

    def _pass(self) -> None:
        with self._once:
            if self.admitted:
                return
            self.admitted = True
        self._admit()

    def _ask(self) -> None:
        gui = self.client.gui
        modal = gui.add_modal("Access token")
        with modal:
            gui.add_markdown(
                "This knotlab app asks for its access token (printed where it was started). "
                "This browser keeps it, so it is asked once."
            )
            with gui.add_form(None) as form:
                field = gui.add_text("Access token", "")
            enter = gui.add_button("Enter", color="green")
            wrong = gui.add_markdown("")

        def submit() -> None:
            given = field.value
            if not token_matches(given, self._token):
                time.sleep(WRONG_PAUSE_S)
                log.warning("client %s: a wrong access token", self.client.client_id)
                wrong.content = "**That is not this app's access token.** Try again."
                return
            self.client.local_storage.set_item(TOKEN_KEY, given.strip())
            modal.close()
            self._pass()

        enter.on_click(lambda _e: submit())
        form.on_submit(lambda _e: submit())

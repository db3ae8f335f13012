"""The viewer's messages: the line under the status and the notification in the tab that acted
(or in every tab), and when the line goes again. A part of
:class:`~lidarloc.app.viewer.app.Viewer`."""

from __future__ import annotations

import time

from .camera import tab_may_close
from .style import ERROR_SHOWN_S, MESSAGE_SHOWN_S, error_markdown


class Messages:
    """A part of :class:`~lidarloc.app.viewer.app.Viewer` (see the module docstring)."""

    def show_message(
        self,
        text: str,
        error: bool = False,
        client=None,
        everyone: bool = False,
        title: str | None = None,
        keep: bool = False,
    ) -> None:
        """A message under the status and as a notification where the user looks: to
        ``client``, else to the tab whose action is being handled, or to every open tab with
        ``everyone`` (what no tab asked for: a failed scan, a failed start). ``title``: the
        notification's (default: from the kind of message). Under the status it goes when its
        notification does (a refusal left there read as the run's state long after), unless
        ``keep``: what stays true until the user acts (a failed step, a failed start)."""
        with self._gui_gate:
            if self.closed:  # the server has stopped (or is stopping): nobody would see it
                return
            self._show_message(text, error, client, everyone, title, keep)

    def _show_message(
        self, text: str, error: bool, client, everyone: bool, title: str | None, keep: bool = False
    ) -> None:
        self._message = text
        shown_for = ERROR_SHOWN_S if error else MESSAGE_SHOWN_S
        self._message_until = None if keep or not text else time.monotonic() + shown_for
        self.controls.message.content = error_markdown(text) if error else text
        self.controls.message.visible = bool(text)
        if not text:
            return
        client = client if client is not None else getattr(self._acting, "client", None)
        open_tabs = self.server.get_clients()
        tabs = [client] if client is not None else (list(open_tabs.values()) if everyone else [])
        # a tab already closed gets nothing; one closing meanwhile drops it (tab_may_close)
        tabs = [t for t in tabs if t.client_id in open_tabs]
        if title is None:
            title = (
                "lidarloc" if not error else "lidarloc: refused" if text.startswith("refused") else "lidarloc: error"
            )
        for tab in tabs:
            try:
                with tab_may_close(tab):
                    tab.add_notification(title, text, color="red" if error else "blue", auto_close_seconds=shown_for)
            except Exception:  # the tab may have closed meanwhile; the panel message stays
                pass

    @property
    def message(self) -> str:
        """The newest message said (also once it is no longer shown)."""
        return self._message

    def _expire_message(self) -> None:
        """The message under the status goes when its time is up (display thread, gate held)."""
        until = self._message_until
        if until is not None and time.monotonic() >= until:
            self._message_until = None
            self.controls.message.visible = False

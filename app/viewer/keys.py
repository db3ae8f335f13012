"""Keyboard shortcuts: space plays and pauses, ← and → step back and forward on the timeline (→ at
the newest scan processes one more).

viser's own hotkeys (command palette commands) fire whatever has the focus: with the timeline's
slider focused, ← moved the slider and the timeline both (two steps per press), and a focused
button got space twice (its own click, then the shortcut); the arrows also turn viser's camera.
So the page gets a small script instead: a key listener that runs first (capture phase on the
window), leaves keys alone while the focus is on a control that uses them (a text or number
field, a slider, a button, a dropdown), and otherwise presses the panel's own buttons (Play or
Pause, the timeline's ◀ and ▶) and stops the key there, so the camera does not turn. Pressing the
buttons keeps one path for every action: the same handlers, refusals and messages as a click.

The script travels in an HTML element of the panel: an image that cannot load runs it from its
error handler (markup set as HTML runs no ``<script>``). It installs itself once per tab."""

from __future__ import annotations

from .timeline import BACK, FORWARD

#: the buttons each key presses (their labels); space takes whichever of Play / Pause is shown
KEY_BUTTONS = {"Space": ("Play", "Pause"), "ArrowLeft": (BACK,), "ArrowRight": (FORWARD,)}

_SCRIPT = """(() => {
  if (window.__lidarlocKeys) return;
  window.__lidarlocKeys = true;
  const keys = %(keys)s;
  const roles = ['slider', 'button', 'textbox', 'combobox', 'listbox', 'option', 'menuitem', 'tab', 'spinbutton'];
  const busy = (el) => !!el && el !== document.body && (el.isContentEditable
      || /^(INPUT|TEXTAREA|SELECT|BUTTON)$/.test(el.tagName) || roles.includes(el.getAttribute('role')));
  const press = (labels) => {
    for (const b of document.querySelectorAll('button')) {
      if (labels.includes(b.textContent.trim()) && !b.disabled) { b.click(); return true; }
    }
    return false;
  };
  window.addEventListener('keydown', (e) => {
    const labels = keys[e.code];
    if (!labels || e.ctrlKey || e.metaKey || e.altKey || e.shiftKey) return;
    if (busy(e.target) || busy(document.activeElement)) return;
    if (e.code === 'Space' && e.repeat) return;
    if (press(labels)) { e.preventDefault(); e.stopImmediatePropagation(); }
  }, true);
})();"""


def shortcuts_html() -> str:
    """The panel element that carries the key listener (and says which keys do what)."""
    import json

    script = _SCRIPT % {"keys": json.dumps(KEY_BUTTONS)}
    handler = script.replace("&", "&amp;").replace('"', "&quot;")
    return (
        f'<img alt="" style="display:none" src="data:image/png;base64,AA==" onerror="{handler}">'
        "<small>Keys: <b>space</b> play / pause · <b>←</b> <b>→</b> one scan back / forward "
        "(when no field or slider has the focus)</small>"
    )


def add_shortcuts(gui):
    """The shortcuts' element on ``gui`` (the server's: every tab gets it)."""
    return gui.add_html(shortcuts_html())

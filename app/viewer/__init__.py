"""The live browser viewer (viser): the prior map, the particle filter's state after every scan,
the last scan-to-map match, and the controls to drive and perturb the localizer.

Threads. A :class:`~lidarloc.app.viewer.player.Player` thread calls ``localizer.step()``; each
snapshot it returns is recorded in a :class:`~lidarloc.app.viewer.history.History` (cheap appends)
and left in a one-slot mailbox. A display thread wakes up, takes the newest snapshot (skipping any
it had no time for) and updates the scene and panels. GUI callbacks run on viser's worker threads;
they only flip player flags or call the localizer's thread-safe setters. Nothing here holds a lock
the localizer waits on, so the display never slows the filter down.

Scene state is shared by all browser tabs (one scene, sent once to each client: the map is static
and never re-sent per scan); the camera and its controls are per tab.

Modules: ``serve`` starts a viewer (``serve``, ``serve_until_interrupted``); ``app`` is the
:class:`~lidarloc.app.viewer.app.Viewer` that wires the panel to the localizer; ``panel`` builds the
controls, ``params`` knows the live parameters' labels and units, ``readouts`` fills the progress
bar and status, ``plots`` the plots on one scan axis, ``legend`` explains every colour, ``scene``
draws the 3D nodes (with ``shapes``), ``camera`` moves each tab's camera, ``ground`` turns pointer picks into places
on the map, ``history`` keeps the per-scan figures, ``style`` holds the look. ``why`` hosts the "why"
views (``why_residuals``, ``why_surface``, ``why_particle``, ``s2m_detail``), their background
thread (``why_worker``) and colours (``why_style``).

Time travel: ``travel`` is the viewer's handle on it — ``recorder`` records every run the viewer
plays (first start, restarts, branches) into its own folder, ``recorded`` reads a recording back
(a branch's first steps from its original), ``timeline`` is the slider and its buttons, ``compare``
the table of two runs' figures, and ``runs`` opens finished runs (``lidarloc view --run``).
"""

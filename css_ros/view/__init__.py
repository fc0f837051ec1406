"""``css_view``: the semantic splat in a browser (offline maps and, with ``--live``, a running node)."""

"""Topic clients of a running `css_node` (next-best-view loop)."""

"""Cell-based objects, Nürnberg 2011 (seed 004): tileable cell tiles, split cells, membership
maps and a ray tracer for first hit, self-reflection and refraction."""

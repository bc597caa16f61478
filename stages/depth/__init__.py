"""Depth stage: plane sweep, plane fill and field fill for photos-only captures."""

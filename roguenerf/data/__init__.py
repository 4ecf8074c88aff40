"""Scenes: one type, readers for the formats users have, toy scenes and degradations."""

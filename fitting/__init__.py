"""Recovering BRDF parameters from target renders (see issue: fitting). Not implemented yet."""

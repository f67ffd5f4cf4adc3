"""Actor sources: where the human partner's motion comes from (file replay, live UDP, synthetic)."""

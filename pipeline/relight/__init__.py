"""The relight stage (§5.2–5.4) and what it alone uses: the G-buffer, the object's surfels, the room's shadow, self-reflection, adaptive shading."""

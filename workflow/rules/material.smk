# Rules of the material stage.

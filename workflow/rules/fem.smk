# Rules of the fem stage.

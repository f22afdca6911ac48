"""The scenes shipped with elastreg (beam.toml, phantom.toml), read by service.scene.builtin_scene."""

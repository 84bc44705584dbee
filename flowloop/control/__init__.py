"""Closing the loop on speed and heat: flow caps for G-code moves, the
reactive grip rule, the predictive grip model and the hotend thermal model."""

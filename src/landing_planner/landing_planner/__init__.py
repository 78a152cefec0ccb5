"""Landing state machine (paper section 3.3), smooth reference generator and horizontal
position controller.
"""

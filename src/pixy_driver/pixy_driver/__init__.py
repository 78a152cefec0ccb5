"""CMUcam5 Pixy (IR-LOCK) block-protocol driver over serial or UDP."""

"""The VL53L8CX 8x8 multizone time-of-flight sensor: the bridge's frame format (``protocol``), the serial
driver, the I2C driver, and a device emulator that speaks the bridge's protocol."""

"""The edge: MQTT service, journal, recorder, PLC bridge, clocks and payloads."""

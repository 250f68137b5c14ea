"""The drive's voltage range: the amplifier input of the paper's valve, 0..10 V, centred at 5 V (the spool's
mid position; the identification signals swing about it and the safe voltage defaults to it)."""

COMMAND_MIN_V = 0.0
COMMAND_MAX_V = 10.0
CENTRE_VOLTAGE_V = 0.5 * (COMMAND_MIN_V + COMMAND_MAX_V)
HALF_SPAN_V = 0.5 * (COMMAND_MAX_V - COMMAND_MIN_V)

"""A base on a CAN bus: python-can for the bus, cantools and a DBC file for the frames
(:mod:`drivers.can.driver`); the DBC files robotd ships are in ``drivers/can/dbc``."""

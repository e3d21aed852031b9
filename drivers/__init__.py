"""Device interfaces and their implementations over pyserial and pyusb."""

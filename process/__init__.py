"""Body model, capture methods (DeMoCap, EventCap), metrics and exporters."""

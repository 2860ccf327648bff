"""How a criterion is judged: DESIGN's metrics (`metrics`), evaluation on held-out scenes per
scene (`evaluate`, `generalisation`), calibration of the model's offset and flip's c
(`calibrate`), charts (`plots`).
"""

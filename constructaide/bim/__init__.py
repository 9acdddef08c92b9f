"""The BIM as files give it (pure: ifcopenshell, numpy; no bus): IFC geometry and properties (:mod:`.ifc`), the site
model they make (:mod:`.model`) and construction schedules from IFC, CSV, MS Project XML or P6 XER (:mod:`.schedule`).
The ingest node publishes it; the batch register command reads it for the model-outline polish."""

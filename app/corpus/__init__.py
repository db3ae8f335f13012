"""``lidarloc corpus``: one localization run per drive of a corpus file, with each drive's health
(where along the drive it fitted poorly, was late, or was localized and wrong), so that a change
of a parameter, a map or the code shows where it made things worse."""
